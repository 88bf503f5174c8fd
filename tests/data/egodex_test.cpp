// EgoDex reader on HDF5 files written here with the HDF5 C API, paired with mp4s from our
// VideoWriter.
#include "data/egodex.h"

#include <hdf5.h>
#include <torch/torch.h>

#include <fstream>

#include "core/error.h"
#include "data/clip_loader.h"
#include "data/episode_clip.h"
#include "io/video.h"
#include "test_util.h"

namespace fs = std::filesystem;

namespace dojo::data {
namespace {

void write_f32(hid_t file, const std::string& name, const std::vector<hsize_t>& dims,
               const std::vector<float>& data) {
  const hid_t lcpl = H5Pcreate(H5P_LINK_CREATE);
  H5Pset_create_intermediate_group(lcpl, 1);
  const hid_t space = H5Screate_simple(static_cast<int>(dims.size()), dims.data(), nullptr);
  const hid_t ds = H5Dcreate2(file, name.c_str(), H5T_NATIVE_FLOAT, space, lcpl, H5P_DEFAULT, H5P_DEFAULT);
  ASSERT_GE(ds, 0) << name;
  H5Dwrite(ds, H5T_NATIVE_FLOAT, H5S_ALL, H5S_ALL, H5P_DEFAULT, data.data());
  H5Dclose(ds);
  H5Sclose(space);
  H5Pclose(lcpl);
}

void write_string_attribute(hid_t file, const std::string& name, const std::string& value, bool variable) {
  const hid_t type = H5Tcopy(H5T_C_S1);
  H5Tset_size(type, variable ? H5T_VARIABLE : value.size() + 1);
  const hid_t space = H5Screate(H5S_SCALAR);
  const hid_t attr = H5Acreate2(file, name.c_str(), type, space, H5P_DEFAULT, H5P_DEFAULT);
  if (variable) {
    const char* p = value.c_str();
    H5Awrite(attr, type, &p);
  } else {
    H5Awrite(attr, type, value.c_str());
  }
  H5Aclose(attr);
  H5Sclose(space);
  H5Tclose(type);
}

// Camera at (0, 1.5, 0), identity rotation on even frames and 90 degrees about Y on odd ones;
// left hand at (1 + 0.01 k, 1.5, 2), right hand at (-1, 1.5, 2).
std::vector<float> camera_transforms(int64_t n) {
  std::vector<float> t;
  for (int64_t k = 0; k < n; ++k) {
    const bool rotated = k % 2 == 1;
    const float r[3][3] = {{rotated ? 0.f : 1.f, 0.f, rotated ? 1.f : 0.f},
                           {0.f, 1.f, 0.f},
                           {rotated ? -1.f : 0.f, 0.f, rotated ? 0.f : 1.f}};
    const float p[3] = {0.f, 1.5f, 0.f};
    for (int i = 0; i < 3; ++i) t.insert(t.end(), {r[i][0], r[i][1], r[i][2], p[i]});
    t.insert(t.end(), {0.f, 0.f, 0.f, 1.f});
  }
  return t;
}

std::vector<float> hand_transforms(int64_t n, float x0, float dx) {
  std::vector<float> t;
  for (int64_t k = 0; k < n; ++k)
    t.insert(t.end(), {1, 0, 0, x0 + dx * k, 0, 1, 0, 1.5f, 0, 0, 1, 2.f, 0, 0, 0, 1});
  return t;
}

// One EgoDex episode: <dir>/<k>.hdf5 with `rows` rows and <k>.mp4 with `video_frames` frames
// (grey level 10 + 4 i), `first` shifting the levels.
void make_episode(const fs::path& hdf5, int64_t rows, int64_t video_frames, const std::string& description,
                  bool variable_string = true, bool with_video = true) {
  fs::create_directories(hdf5.parent_path());
  const hid_t file = H5Fcreate(hdf5.string().c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT);
  ASSERT_GE(file, 0);
  write_f32(file, "/camera/intrinsic", {3, 3}, {500, 0, 16, 0, 500, 16, 0, 0, 1});
  const hsize_t n = static_cast<hsize_t>(rows);
  write_f32(file, "/transforms/camera", {n, 4, 4}, camera_transforms(rows));
  write_f32(file, "/transforms/leftHand", {n, 4, 4}, hand_transforms(rows, 1.f, 0.01f));
  write_f32(file, "/transforms/rightHand", {n, 4, 4}, hand_transforms(rows, -1.f, 0.f));
  write_f32(file, "/transforms/hip", {n, 4, 4}, hand_transforms(rows, 0.f, 0.f));
  write_f32(file, "/confidences/leftHand", {n}, std::vector<float>(rows, 0.9f));
  write_string_attribute(file, "llm_description", description, variable_string);
  write_string_attribute(file, "environment", "kitchen", false);
  H5Fclose(file);
  if (!with_video) return;
  auto levels = (torch::arange(video_frames) * 4 + 10).to(torch::kUInt8);
  const auto frames = levels.view({video_frames, 1, 1, 1}).expand({video_frames, 32, 48, 3}).contiguous();
  io::VideoWriterOptions options;
  options.fps = 30;
  options.keyframe_interval = 8;
  options.crf = 10;
  fs::path mp4 = hdf5;
  io::write_video(mp4.replace_extension(".mp4").string(), frames, options);
}

}  // namespace

TEST(EgoDex, ReadsFramesTextIntrinsicsAndHandMotion) {
  test::TempDir tmp;
  const fs::path root = tmp / "egodex";
  make_episode(root / "part1" / "pick_cup" / "0.hdf5", 20, 20, "Pick up the cup with the right hand.");
  make_episode(root / "part2" / "wipe" / "3.hdf5", 16, 16, "Wipe the table.", /*variable_string=*/false);
  EXPECT_TRUE(looks_like_egodex(root));
  const auto source = open_dataset(root);
  EXPECT_EQ(source->format(), "egodex");
  const auto& ds = dynamic_cast<const EgoDexDataset&>(*source);
  ASSERT_EQ(ds.size(), 2u);
  EXPECT_EQ(ds.info().embodiment, Embodiment::kHuman);
  EXPECT_EQ(ds.info().episodes[0].frames, 20);
  EXPECT_EQ(ds.info().episodes[0].task, "Pick up the cup with the right hand.");
  EXPECT_EQ(ds.info().episodes[1].task, "Wipe the table.");  // fixed-length string attribute
  EXPECT_EQ(ds.info().episodes[1].id, "part2/wipe/3");
  EXPECT_EQ(ds.info().width, 48);
  EXPECT_DOUBLE_EQ(ds.info().fps, 30);

  const auto arrays = ds.read_arrays(0);
  EXPECT_FALSE(arrays.actions.defined());
  ASSERT_EQ(arrays.hidden_motion.sizes(), (std::vector<int64_t>{20, 6}));
  // Even frame: identity camera, offset (1 + 0.01 k, 0, 2). Odd: R_y(90)^T offset = (-2, 0, 1 + 0.01 k).
  const auto m = arrays.hidden_motion;
  EXPECT_NEAR(m[4][0].item<float>(), 1.04f, 1e-5);
  EXPECT_NEAR(m[4][1].item<float>(), 0.f, 1e-5);
  EXPECT_NEAR(m[4][2].item<float>(), 2.f, 1e-5);
  EXPECT_NEAR(m[5][0].item<float>(), -2.f, 1e-5);
  EXPECT_NEAR(m[5][2].item<float>(), 1.05f, 1e-5);
  EXPECT_NEAR(m[4][3].item<float>(), -1.f, 1e-5);  // right hand
  EXPECT_NEAR(m[5][5].item<float>(), -1.f, 1e-5);
  EXPECT_FLOAT_EQ(arrays.meta.at("intrinsic")[0][0].get<float>(), 500.f);
  EXPECT_EQ(ds.read_transforms(0, "hip").sizes(), (std::vector<int64_t>{20, 4, 4}));
  const auto joints = ds.joints(0);
  EXPECT_NE(std::find(joints.begin(), joints.end(), "leftHand"), joints.end());

  const auto frames = ds.read_frames(0, {0, 7, 19});
  ASSERT_EQ(frames.sizes(), (std::vector<int64_t>{3, 32, 48, 3}));
  EXPECT_NEAR(frames[1].to(torch::kFloat32).mean().item<float>(), 10 + 4 * 7, 1.5);
  EXPECT_NEAR(frames[2].to(torch::kFloat32).mean().item<float>(), 10 + 4 * 19, 1.5);
}

TEST(EgoDex, ClipsAreActionFreeAndCarryHiddenMotion) {
  test::TempDir tmp;
  make_episode(tmp / "egodex" / "part1" / "pour" / "0.hdf5", 20, 20, "Pour water.");
  ClipConfig config;
  config.height = config.width = 16;
  config.strides = {1};
  ClipDataset dataset(open_dataset(tmp / "egodex"), config, "all");
  const auto clip = dataset.read(0, make_window(3, 1, 13));  // frames 4..16
  EXPECT_FALSE(clip.has_actions);
  EXPECT_EQ(clip.actions.slice(1, 352).sum().item<float>(), 12.f * 32.f);
  ASSERT_EQ(clip.hidden_motion.sizes(), (std::vector<int64_t>{13, 6}));
  EXPECT_NEAR(clip.hidden_motion[0][0].item<float>(), 1.04f, 1e-5);  // frame 4 (even)
  EXPECT_NEAR(clip.video[12].to(torch::kFloat32).mean().item<float>(), 10 + 4 * 16, 2.0);
}

// A rollout on an EgoDex folder as it is: every frame (no robot stride), resized as asked, the
// latent-action mask for actions, no raw commands.
TEST(EgoDex, RollsOutAsActionFreeVideoAtEveryFrame) {
  test::TempDir tmp;
  make_episode(tmp / "egodex" / "part1" / "pour" / "0.hdf5", 20, 20, "Pour water.");
  RolloutDataOptions options;
  options.height = options.width = 16;
  const RolloutData data(tmp / "egodex", 1, {}, options);
  EXPECT_EQ(data.stride(), 1);
  EXPECT_EQ(data.normalization(), "none");
  const auto clip = data.read(data.find("", "part1/pour/0"));
  ASSERT_EQ(clip.video.sizes(), (std::vector<int64_t>{13, 16, 16, 3}));
  EXPECT_NEAR(clip.video[12].to(torch::kFloat32).mean().item<float>(), 10 + 4 * 13, 2.0);  // frame 13
  EXPECT_TRUE(torch::equal(clip.actions, human_action_placeholder(12)));
  EXPECT_FALSE(clip.raw_baseline.defined());
  EXPECT_DOUBLE_EQ(clip.fps, 30);
  EXPECT_NE(test::error_message([&] {
              data.raw_to_rows(torch::zeros({12, 6}), {});
            }).find("action-free"),
            std::string::npos);
}

TEST(EgoDex, MissingVideoAndBadFilesNameTheFile) {
  test::TempDir tmp;
  const fs::path root = tmp / "egodex";
  make_episode(root / "task" / "0.hdf5", 12, 12, "a");
  make_episode(root / "task" / "1.hdf5", 12, 12, "b", true, /*with_video=*/false);
  EXPECT_EQ(test::error_message([&] { EgoDexDataset::open(root); }),
            (root / "task" / "1.mp4").string() + ": video file missing (paired with 1.hdf5)");
  fs::remove(root / "task" / "1.hdf5");
  // More HDF5 rows than video frames: the missing frames are an error naming the video.
  make_episode(root / "task" / "2.hdf5", 20, 12, "c");
  const auto ds = EgoDexDataset::open(root);
  EXPECT_EQ(test::error_message([&] { ds->read_frames(1, {15}); }),
            (root / "task" / "2.mp4").string() + ": frame 15 outside the video (12 frames, 20 HDF5 rows)");
  // An HDF5 file without /transforms.
  {
    const hid_t file =
        H5Fcreate((root / "task" / "9.hdf5").string().c_str(), H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT);
    write_f32(file, "/camera/intrinsic", {3, 3}, std::vector<float>(9, 1.f));
    H5Fclose(file);
    fs::copy_file(root / "task" / "0.mp4", root / "task" / "9.mp4");
  }
  EXPECT_EQ(test::error_message([&] { EgoDexDataset::open(root); }),
            (root / "task" / "9.hdf5").string() + ": no /transforms group (not an EgoDex file)");
  std::ofstream(root / "task" / "9.hdf5", std::ios::trunc) << "not hdf5";
  EXPECT_EQ(test::error_message([&] { EgoDexDataset::open(root); }),
            (root / "task" / "9.hdf5").string() + ": cannot open as HDF5");
}

TEST(EgoDex, DataInfoJson) {
  test::TempDir tmp;
  make_episode(tmp / "egodex" / "part1" / "pour" / "0.hdf5", 12, 12, "Pour water.");
  const auto r = test::run_dojo("data info " + (tmp / "egodex").string() + " --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto j = nlohmann::json::parse(r.output);
  EXPECT_EQ(j.at("format"), "egodex");
  EXPECT_EQ(j.at("episodes"), 1);
  EXPECT_EQ(j.at("frames"), 12);
  EXPECT_EQ(j.at("embodiments"), nlohmann::json({"human"}));
  EXPECT_EQ(j.at("tasks"), nlohmann::json({"Pour water."}));
}

}  // namespace dojo::data
