// Distillation of the post-trained teacher into the causal few-step student (`dojo distill`).
// Facts: ../shared/reference/self_forcing.md §1-§2.
//
//   trajectories  the teacher's ODE solutions (35 UniPC steps at its trained shift) on training
//                 clips, kept at the student's points: the samples before steps 0, 9, 18, 27
//                 and the final x0, with frame 0 the clip's clean conditioning latent. Written
//                 in shards fingerprinted by teacher, data and sampler, so an interrupted run
//                 keeps what it finished and a changed teacher or dataset rebuilds them.
//   warm-up       the student starts as a copy of the teacher and regresses the teacher's x0 from
//                 those points under the block-causal window mask (a new frame sees itself and
//                 the student's window of earlier frames), each frame at its own random point,
//                 frame 0 clean: x̂0 = x − (t/1000)·v̂, loss mean((x̂0 − x0_teacher)²) over frames ≥ 1.
//                 With counterfactual copies (TrajectorySpec::counterfactual_copies) the teacher's
//                 trajectories also cover each first frame under other clips' actions.
#pragma once

#include <torch/torch.h>

#include <cstdint>
#include <filesystem>
#include <vector>

#include "infer/streaming.h"
#include "models/dit.h"
#include "models/wan_vae.h"
#include "train/latent_cache.h"
#include "train/self_forcing.h"
#include "train/train_util.h"
#include "train/wm_train.h"

namespace dojo::train {

struct TeacherTrajectories {
  torch::Tensor points;            // [N, P, 16, 4, h, w]: the samples at the query steps, then the final x0
  torch::Tensor actions;           // [N, 12, 384]
  std::vector<int64_t> timesteps;  // [P] the teacher's integer timesteps of the points (the last: 0)
  int64_t size() const { return points.defined() ? points.size(0) : 0; }
};

struct TrajectorySpec {
  int teacher_steps = 35;                         // UniPC steps, as released
  std::vector<int> query_steps = {0, 9, 18, 27};  // samples kept before these steps
  // The released query steps scaled to another step count: round(9 i N / 35), i = 0..3.
  static std::vector<int> query_steps_for(int teacher_steps);
  int64_t shard_clips = 64;
  int batch = 16;  // clips through the teacher together
  uint64_t seed = 0;
  // Also solve each clip's ODE this many more times with another clip's actions (clip i with the
  // actions of clip (i + k·stride) mod N, k = 1 ..), from the same first frame and the same noise.
  // With one trajectory per clip the first frame names the clip and the target can be reached
  // without reading the actions; pairs that differ only in the actions make the teacher's response
  // to them part of the regression target.
  int counterfactual_copies = 0;
  // Teacher chunks per trajectory: 1 gives the 4-latent clips (13 frames) the teacher was trained
  // on; K > 1 chains K chunks in latent space (chunk k starts from the x0 of chunk k-1's last
  // latent, with its own 12 actions and noise; the teacher's pixel rollouts re-encode a decoded
  // frame there instead) into 1 + 3 K latents (1 + 12 K frames), so the warm-up also teaches the
  // positions a streaming student reaches after its first 13 frames.
  int chunks = 1;
  // How chunk k > 0 is anchored: false, on chunk k-1's last latent as it is (it holds frames 9-12,
  // where the teacher was trained on a single frame's latent); true, as the teacher's own rollouts
  // are: that chunk decoded to uint8 frames, its last frame encoded alone (needs the tokenizer).
  bool reencode_anchor = false;
  // Whether any chunk is anchored on a re-encoded frame (one chunk anchors nothing).
  bool reencodes_anchors() const { return reencode_anchor && chunks > 1; }
  // The teacher's matmuls under autocast at this precision (bf16: a different trajectory from
  // fp32's, so it is part of the shards' fingerprint); the teacher runs where its weights are.
  Precision precision = Precision::kFloat32;
};

// The teacher's trajectories on `clips` (latents [N, 16, 1 + 3 K, h, w], actions [N, 12 K, 384],
// K = spec.chunks; only each clip's first latent and its actions are read),
// written to / read from dir/shard-<k>.safetensors. `fingerprint` identifies teacher and data;
// shards made from anything else are rebuilt.
// `tokenizer` (on the teacher's device) re-encodes the anchors when spec.reencode_anchor is set.
TeacherTrajectories load_or_build_trajectories(models::ActionDitImpl& teacher, double shift,
                                               const LatentClips& clips, const TrajectorySpec& spec,
                                               const nlohmann::json& fingerprint,
                                               const std::filesystem::path& dir,
                                               models::WanVaeImpl* tokenizer = nullptr);

// The warm-up regression loss of `student` on a batch of trajectory points: frames ≥ 1 each at a
// random point (drawn from `generator`), frame 0 clean, under the block-causal mask of the window
// (and sink: at frame 0's own position). points [B, P, 16, 4, h, w].
torch::Tensor warmup_loss(models::ActionDitImpl& student, const torch::Tensor& points,
                          const torch::Tensor& actions, const std::vector<int64_t>& timesteps,
                          int64_t window_frames, torch::Generator generator, int64_t sink_frames = 0);
// The same with the points chosen: point_index [B, T] (frame 0's the clean one, P - 1), as
// warmup_loss draws it with torch::randint(P, {B, T}, generator).
// `context_offset` (defined: [B, 16, T, h, w], from context_noise_offsets) is added to the input
// frames and to their targets: a clean frame with noise on it is still clean context, and its own
// loss term stays zero.
torch::Tensor warmup_loss_at(models::ActionDitImpl& student, const torch::Tensor& points,
                             const torch::Tensor& actions, const std::vector<int64_t>& timesteps,
                             int64_t window_frames, torch::Tensor point_index, int64_t sink_frames = 0,
                             const torch::Tensor& context_offset = {});

// point_index [B, T] with a share of its rows (drawn from `generator`) turned into a clean context:
// in such a row, frames before a frontier drawn uniformly in [1, T) take the clean point P - 1.
// Share 0 draws nothing and returns point_index unchanged.
torch::Tensor with_clean_context(torch::Tensor point_index, double share, int64_t points,
                                 torch::Generator& generator);

// Gaussian noise for the clean frames after frame 0 (those at point P - 1 in point_index [B, T]),
// one level per clip drawn uniformly in [0, max_level): the student streams on latents it made
// itself, and a context it cannot copy exactly pushes it to read the actions. [B, 16, T, h, w] on
// the CPU, zero elsewhere; max_level 0 draws nothing and returns an undefined tensor.
torch::Tensor context_noise_offsets(const torch::Tensor& point_index, int64_t points,
                                    at::IntArrayRef latent_shape, double max_level,
                                    torch::Generator& generator);

// A warm-up batch's trajectory indices: trajectory j is clip j % N under copy j / N's actions
// (N = the mixture's clips, `copies` per clip). Weighted: the clip from `mixture`, the copy
// uniformly; unweighted: every trajectory alike (the stream drawn before weights existed).
torch::Tensor draw_trajectories(const MixtureIndex& mixture, int64_t copies, int64_t count,
                                torch::Generator& generator);  // [count] int64

enum class DistillStage { kWarmup, kSelfForcing };
DistillStage parse_distill_stage(const std::string& text);  // warmup | self-forcing

struct DistillJob {
  DistillStage stage = DistillStage::kWarmup;
  std::vector<LatentCacheSpec> data;  // robot clips, encoded by the teacher's tokenizer
  // One mixture weight per dataset of `data`, as WmTrainJob::weights: dataset d fills weight[d] /
  // sum of the batches (warm-up: of its clips' trajectories, every copy alike). Empty: every clip
  // alike. Recorded in the checkpoint's trainer state ("mixture").
  std::vector<double> weights;
  std::filesystem::path teacher;  // the post-trained teacher checkpoint
  std::filesystem::path out;      // out/latents-<i>, out/trajectories/, out/checkpoint, out/loss.csv
  std::filesystem::path init;     // self-forcing: the warmed-up student; warm-up: a student to start from
  infer::StudentConfig student;   // warm-up: the student made; self-forcing: from init's config
  SelfForcingOptions self_forcing;
  // rank > 0: the student trains LoRA adapters alone (warm-up: on the teacher's weights;
  // Self-Forcing: fresh adapters on the warmed-up student, its own folded in), every other weight
  // frozen; the critic trains in full. Adapters kept apart in the checkpoint, folded in at load.
  models::LoraConfig lora;
  TrajectorySpec trajectories;
  WmTrainOptions options;  // lr, weight decay, clipping, EMA (flow-matching fields unused)
  int batch_size = 8;      // the global batch of a step, over every process
  int64_t accumulate = 1;  // micro-batches per step and process (data_parallel.h)
  int64_t steps = 1000;
  double time_budget_s = 0;
  int64_t save_every = 200;
  uint64_t seed = 0;
  // Warm-up: share of a step's clips trained as the student streams, on a clean context: frames
  // before a random frontier k (1 <= k < T) at their clean point, frames from k on at random
  // points (with_clean_context). The student streams on its own clean frames, which the per-frame
  // draws (frame f clean with probability 1/P) almost never show it for late frames.
  double clean_context_share = 0;
  // Warm-up: noise on the clean context frames (context_noise_offsets), level ~ U(0, this).
  double context_noise = 0;
  // Under data parallelism, each process keeps 1/world of the AdamW moments (student, and in
  // Self-Forcing the critic too; WmTrainer::shard_optimizer_state): the same bits as without.
  bool zero1 = false;
  // Where the teacher, student and critic run and at what precision (bf16: their forward passes
  // under autocast, weights, moments and losses float32, as WmTrainer); every draw stays on the
  // CPU, so a seed gives the same batches on any device. Checkpoints are CPU float32 either way.
  torch::Device device = torch::kCPU;
  Precision precision = Precision::kFloat32;
  // > 0: intra-op threads once the latent caches are ready (as WmTrainJob::matmul_threads): the
  // trajectories and the training are matmul-bound, encoding the caches is not.
  int matmul_threads = 0;
};

struct DistillResult {
  int64_t steps = 0, clips = 0;  // self-forcing: iterations (generator + critic updates)
  double first_loss = 0, last_loss = 0;
  double fixed_batch_loss_start = 0, fixed_batch_loss_end = 0;  // EMA student, fixed points
  double seconds = 0;
};

// Warm-up: trajectories, then the regression. Self-forcing: DMD from the warmed-up student on
// 49-frame clips, the critic in out/critic. Both resume from out/checkpoint, a world-model
// checkpoint (the EMA student) whose config carries the "student" entry and the teacher's action
// ranges. Fixed-batch loss: warm-up, the regression loss; self-forcing, the latent MSE of the EMA
// student's full-length rollouts against the clips.
DistillResult run_distillation(const DistillJob& job);

}  // namespace dojo::train
