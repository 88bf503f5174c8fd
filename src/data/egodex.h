// EgoDex (Apple's egocentric dexterous-manipulation set) read as an action-free EpisodeSource.
//
//   ROOT/partN/<task>/<k>.hdf5 + <k>.mp4     HDF5 row i <-> video frame i (30 Hz)
//   /camera/intrinsic                         [3, 3] float
//   /transforms/<joint>                       [N, 4, 4] SE(3) in the ARKit world frame (Y up):
//                                             camera, hip, leftHand, rightHand, finger joints, ...
//   /confidences/<joint>                      [N] (optional)
//   root attributes                           llm_description, llm_description2, task, ...
//
// Clips are human video (latent-action mask, no robot actions). The hand motion is kept as
// hidden_motion, never used for training: [N, 6] = left and right wrist positions (xyz) in
// the camera frame, camera^-1 * hand. HDF5 is read with the C API (libhdf5 from Debian) under a
// process-wide lock, since Debian's serial libhdf5 is not thread-safe.
#pragma once

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "data/episode_source.h"

namespace dojo::data {

// True when the tree under `dir` holds an .hdf5 file with an .mp4 of the same name beside it.
bool looks_like_egodex(const std::filesystem::path& dir);

// The joints EgoDex's hidden motion uses.
inline constexpr const char* kEgoDexCamera = "camera";
inline constexpr const char* kEgoDexLeftHand = "leftHand";
inline constexpr const char* kEgoDexRightHand = "rightHand";

class EgoDexDataset : public EpisodeSource {
 public:
  // Finds every <k>.hdf5 with its <k>.mp4 (sorted by path). An .hdf5 without its .mp4, or an
  // HDF5 file without /transforms, throws dojo::Error naming the file.
  static std::shared_ptr<EgoDexDataset> open(const std::filesystem::path& root);

  std::string format() const override { return "egodex"; }
  const std::filesystem::path& root() const override { return root_; }
  const DatasetInfo& info() const override { return info_; }
  std::string episode_location(size_t index) const override { return episodes_.at(index).hdf5.string(); }
  at::Tensor read_frames(size_t index, const std::vector<int64_t>& frames) const override;
  // hidden_motion [N, 6]; meta: description, task, intrinsic (3x3), joints.
  EpisodeData read_arrays(size_t index) const override;
  nlohmann::json describe() const override;

  // One joint's transforms, [N, 4, 4] float32; throws naming the file when absent.
  at::Tensor read_transforms(size_t index, const std::string& joint) const;
  at::Tensor read_intrinsic(size_t index) const;  // [3, 3]
  std::vector<std::string> joints(size_t index) const;

  struct Episode {
    std::filesystem::path hdf5, video;
    int64_t frames = 0;
    std::string description, task;
  };
  const std::vector<Episode>& episodes() const { return episodes_; }

 private:
  std::filesystem::path root_;
  DatasetInfo info_;
  std::vector<Episode> episodes_;
};

}  // namespace dojo::data
