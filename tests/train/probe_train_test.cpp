#include "train/probe_train.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "core/checkpoint.h"
#include "data/episode_store.h"
#include "eval/keypoint_metrics.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo::train {
namespace {

// A capped run on synthetic episodes: the probe learns to find the block (error well below a
// guess at the centre of the frame) and tells the robot's block from the human's.
TEST(ProbeTrain, LearnsToFindTheBlock) {
  test::OneThread one;
  test::TempDir tmp;
  for (const std::string emb : {"robot", "human"}) {
    test::SyntheticOptions o;
    o.embodiment = emb;
    o.episodes = 16;  // enough tables and paths that only the block generalises
    o.frames = 12;
    o.val_episodes = 2;
    o.seed = 1;  // the same tables and paths for both: only the block tells them apart
    test::write_synthetic_dataset(tmp / emb, o);
  }
  ProbeTrainJob job;
  job.datasets = {tmp / "robot", tmp / "human"};
  job.out = tmp / "probe";
  job.model.size = 32;
  job.model.width = 16;
  job.steps = 400;
  job.batch_size = 16;
  job.save_every = 100;
  const auto r = run_probe_training(job);
  EXPECT_EQ(r.steps, 400);
  EXPECT_EQ(Checkpoint::open(tmp / "probe" / "checkpoint").step(), 400);

  auto probe = models::load_keypoint_probe(tmp / "probe" / "checkpoint");
  const auto a = eval::probe_accuracy(probe, job.datasets, "val");
  std::printf("held-out: %.2f px, recall %.3f, false positives %.3f\n", a.error_px, a.recall,
              a.false_positive);
  EXPECT_EQ(a.frames, 48);     // 2 held-out episodes of each embodiment
  EXPECT_LT(a.error_px, 3.0);  // on 32x32 frames; guessing the centre is ~8 px off
  EXPECT_GT(a.recall, 0.9);
  EXPECT_LT(a.false_positive, 0.1);

  // Resuming a finished job does nothing; a longer one continues.
  job.steps = 410;
  EXPECT_EQ(run_probe_training(job).steps, 410);
}

TEST(ProbeTrain, DatasetsWithoutKeypointsFailClearly) {
  test::TempDir tmp;
  test::write_synthetic_dataset(tmp / "robot", {});
  // Drop the keypoints from info.json: a dataset from elsewhere.
  auto info = data::EpisodeStore::open(tmp / "robot").info();
  info.keypoint_names.clear();
  data::write_dataset_info(tmp / "robot", info);
  ProbeTrainJob job;
  job.datasets = {tmp / "robot"};
  job.out = tmp / "probe";
  EXPECT_NE(test::error_message([&] { run_probe_training(job); }).find("no simulator keypoints"),
            std::string::npos);
}

}  // namespace
}  // namespace dojo::train
