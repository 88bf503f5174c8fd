// Small episode datasets written through the episode store without the simulator, for tests that
// need data but not DojoSim (they run in a DOJO_WITH_SIM=OFF build too). A "robot" episode shows a
// dark arm block moving over a coloured table as its 6-d actions command; a "human" episode shows
// a skin-coloured hand block with no actions and its motion as hidden_motion. Both carry three
// "keypoints" the way the simulator records them: the block's centre and its top-left and
// bottom-right corners.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>

#include "data/episode_store.h"

namespace dojo::test {

struct SyntheticOptions {
  std::string embodiment = "robot";  // robot | human
  int episodes = 3;
  int frames = 24;
  int size = 32;  // square frames
  uint64_t seed = 0;
  int val_episodes = 0;  // the last ones are split "val"
  // A second camera, "side": the same scene mirrored left to right (info.json cameras ego, side).
  bool side_camera = false;
#ifdef DOJO_WITH_MEDIA
  data::VideoFormat video_format = data::VideoFormat::kMp4;
#else
  data::VideoFormat video_format = data::VideoFormat::kRaw;  // this build reads no video file
#endif
};

// Writes DIR/info.json and DIR/episodes/NNNNNN like `dojo sim generate` does.
void write_synthetic_dataset(const std::filesystem::path& dir, const SyntheticOptions& options);

}  // namespace dojo::test
