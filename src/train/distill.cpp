#include "train/distill.h"

#include <ATen/CPUGeneratorImpl.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <deque>
#include <optional>
#include <sstream>

#include "core/atomic_file.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/log.h"
#include "core/progress.h"
#include "core/runtime.h"
#include "core/safetensors.h"
#include "data/episode_source.h"
#include "data/multi_view.h"
#include "diffusion/samplers.h"
#include "train/data_parallel.h"
#include "train/train_loop.h"
#include "train/train_util.h"

namespace fs = std::filesystem;

namespace dojo::train {

namespace {

// The teacher's ODE solution for clips [n, 16, 4, h, w] from per-clip noise; the samples before
// the query steps and the final x0, frame 0 the clean conditioning latent: [n, P, 16, 4, h, w].
torch::Tensor teacher_points(models::ActionDitImpl& teacher, const diffusion::SigmaSchedule& schedule,
                             const torch::Tensor& x0, const torch::Tensor& actions,
                             const torch::Tensor& noise, const std::vector<int>& query_steps,
                             Precision precision) {
  torch::NoGradGuard no_grad;
  AutocastGuard autocast(x0.device().type(), precision);
  auto mask = torch::zeros_like(x0.narrow(1, 0, 1));  // [n, 1, 4, h, w]
  mask.narrow(2, 0, 1).fill_(1);
  const diffusion::VelocityFn velocity = [&](const torch::Tensor& x, double, int64_t timestep) {
    models::DitInputs in;
    in.timesteps =
        torch::full({x.size(0), 1}, static_cast<double>(timestep), x.options().dtype(torch::kFloat32));
    in.actions = actions;
    return models::denoise_velocity(teacher, in, x, x0, noise, mask);
  };
  std::vector<torch::Tensor> trajectory;
  diffusion::sample_flow(velocity, noise, schedule, diffusion::Solver::kUniPC, &trajectory);
  std::vector<torch::Tensor> points;
  for (int q : query_steps) points.push_back(trajectory.at(static_cast<size_t>(q)));
  points.push_back(trajectory.back());
  auto out = torch::stack(points, 1);                                                // [n, P, 16, 4, h, w]
  out.select(3, 0).copy_(x0.select(2, 0).unsqueeze(1).expand_as(out.select(3, 0)));  // frame 0 clean
  return out;
}

// The teacher's rollout of `chunks` chained chunks for clips (first latents [m, 16, 1, h, w],
// actions [m, 12 chunks, 384]) at the query points: [m, P, 16, 1 + 3 chunks, h, w]. Chunk k starts
// from the final x0 of chunk k-1's last latent, in latent space as the student streams (the
// teacher's own pixel rollouts decode that chunk and re-encode its last frame instead: a
// single-frame latent where this one holds frames 9-12, an approximation); its noise is drawn per
// clip (clip_ids) and chunk. Chunk c with seed s draws what chunk 0 with seed s + 1000003·c draws.
// Computed where the teacher's weights are; returned on the CPU.
torch::Tensor chained_teacher_points(models::ActionDitImpl& teacher, const diffusion::SigmaSchedule& schedule,
                                     const torch::Tensor& first, const torch::Tensor& actions,
                                     const std::vector<int64_t>& clip_ids, const TrajectorySpec& spec,
                                     models::WanVaeImpl* tokenizer) {
  const int64_t P = static_cast<int64_t>(spec.query_steps.size()) + 1;
  const auto device = teacher.parameters().front().device();
  auto anchor = first.to(device);  // [m, 16, 1, h, w]
  std::vector<torch::Tensor> pieces;
  for (int c = 0; c < spec.chunks; ++c) {
    std::vector<torch::Tensor> noise;
    for (int64_t id : clip_ids) {
      // Chunk 0 draws what a one-chunk trajectory of the clip draws, so both share their first chunk.
      auto g = step_generator(spec.seed + 1000003ULL * static_cast<uint64_t>(c), id);
      noise.push_back(torch::randn({first.size(1), 4, first.size(3), first.size(4)}, g));
    }
    const auto x0 = torch::cat({anchor, torch::zeros_like(anchor).expand({-1, -1, 3, -1, -1})}, 2);
    const auto points = teacher_points(teacher, schedule, x0, actions.narrow(1, 12 * c, 12).to(device),
                                       torch::stack(noise).to(device), spec.query_steps,
                                       spec.precision);  // [m, P, 16, 4, h, w]
    pieces.push_back(c == 0 ? points : points.narrow(3, 1, 3));
    if (c + 1 == spec.chunks) break;                // the last chunk anchors nothing
    const auto chunk_x0 = points.select(1, P - 1);  // [m, 16, 4, h, w]
    if (spec.reencode_anchor) {
      // As WorldModel::rollout: the chunk's frames as uint8, the last one encoded on its own.
      torch::NoGradGuard no_grad;
      const auto frames = models::model_to_video(tokenizer->decode_latents(chunk_x0));  // [m, 13, H, W, 3]
      anchor = tokenizer->encode_latents(models::video_to_model(frames.narrow(1, 12, 1).to(device)));
    } else {
      anchor = chunk_x0.narrow(2, 3, 1);  // the chunk's last latent, clean
    }
  }
  return torch::cat(pieces, 3).to(torch::kCPU);
}
}  // namespace

std::vector<int> TrajectorySpec::query_steps_for(int teacher_steps) {
  DOJO_CHECK(teacher_steps >= 4,
             "distill: the teacher needs at least 4 steps (got " + std::to_string(teacher_steps) + ")");
  std::vector<int> q;
  for (int i = 0; i < 4; ++i) q.push_back(static_cast<int>(std::lround(9.0 * i * teacher_steps / 35.0)));
  return q;
}

TeacherTrajectories load_or_build_trajectories(models::ActionDitImpl& teacher, double shift,
                                               const LatentClips& clips, const TrajectorySpec& spec,
                                               const nlohmann::json& fingerprint, const fs::path& dir,
                                               models::WanVaeImpl* tokenizer) {
  DOJO_CHECK(spec.chunks >= 1, "distill: trajectories need at least one teacher chunk");
  DOJO_CHECK(!spec.reencodes_anchors() || tokenizer != nullptr,
             "distill: re-encoded anchors need the tokenizer");
  DOJO_CHECK(clips.latents.dim() == 5 && clips.latents.size(2) == 1 + 3 * spec.chunks &&
                 clips.actions.size(1) == 12 * spec.chunks,
             "distill: trajectories of " + std::to_string(spec.chunks) + " teacher chunks need clips of " +
                 std::to_string(1 + 12 * spec.chunks) + " frames (" + std::to_string(1 + 3 * spec.chunks) +
                 " latent frames)");
  const auto schedule = diffusion::flow_sigma_schedule(spec.teacher_steps, shift);
  for (int q : spec.query_steps)
    DOJO_CHECK(q >= 0 && q < spec.teacher_steps, "distill: query step " + std::to_string(q) +
                                                     " outside the " + std::to_string(spec.teacher_steps) +
                                                     " teacher steps");
  TeacherTrajectories out;
  for (int q : spec.query_steps) out.timesteps.push_back(schedule.timesteps.at(static_cast<size_t>(q)));
  out.timesteps.push_back(0);
  DOJO_CHECK(spec.counterfactual_copies >= 0 && (spec.counterfactual_copies == 0 || clips.size() >= 2),
             "distill: counterfactual trajectories need at least 2 clips");
  nlohmann::json meta = {{"fingerprint", fingerprint},
                         {"teacher_steps", spec.teacher_steps},
                         {"shift", shift},
                         {"query_steps", spec.query_steps},
                         {"seed", spec.seed}};
  if (spec.counterfactual_copies > 0) meta["counterfactual_copies"] = spec.counterfactual_copies;
  if (spec.chunks > 1) meta["chunks"] = spec.chunks;
  if (spec.reencodes_anchors()) meta["anchor"] = "reencoded";
  if (spec.precision != Precision::kFloat32) meta["precision"] = dojo::to_string(spec.precision);
  fs::create_directories(dir);
  // Trajectory j: clip j % N's first frame and noise, with the actions of clip (j + k·stride) % N
  // for copy k = j / N (k = 0: its own). The stride spreads the copies over far-apart clips, whose
  // motions differ more than a neighbouring window's of the same episode.
  const int64_t clip_count = clips.size(), copies = 1 + spec.counterfactual_copies;
  const int64_t stride = std::max<int64_t>(1, clip_count / copies / 2 + 1);
  DOJO_CHECK(spec.counterfactual_copies * stride < clip_count,
             "distill: " + std::to_string(spec.counterfactual_copies) +
                 " counterfactual copies need more than " +
                 std::to_string(spec.counterfactual_copies * stride) + " clips (got " +
                 std::to_string(clip_count) + "), or a copy would get its own clip's actions");
  std::vector<int64_t> action_source(static_cast<size_t>(clip_count * copies));
  for (int64_t j = 0; j < clip_count * copies; ++j)
    action_source[static_cast<size_t>(j)] = (j % clip_count + (j / clip_count) * stride) % clip_count;
  const auto action_index = torch::tensor(action_source, torch::kLong);
  const auto all_actions = clips.actions.index_select(0, action_index);  // [N·copies, 12, 384]
  const int64_t n = clip_count * copies, shards = (n + spec.shard_clips - 1) / spec.shard_clips;
  std::vector<torch::Tensor> points, actions;
  auto& group = data_parallel();
  teacher.eval();
  // Under data parallelism each rank first builds its share of the missing shards (shard k on rank
  // k mod world); then every rank reads all of them below.
  const auto build_shard = [&](int64_t k, const fs::path& file, const nlohmann::json& shard_meta,
                               Progress* progress) {
    const int64_t begin = k * spec.shard_clips, count = std::min(spec.shard_clips, n - begin);
    std::vector<torch::Tensor> shard;
    for (int64_t b = begin; b < begin + count; b += spec.batch) {
      const int64_t m = std::min<int64_t>(spec.batch, begin + count - b);
      // Noise per clip (not per trajectory: a counterfactual copy shares its clip's), so the
      // batching does not change the draws.
      std::vector<int64_t> ids;
      for (int64_t j = b; j < b + m; ++j) ids.push_back(j % clip_count);
      const auto first = clips.latents.narrow(2, 0, 1).index_select(0, torch::tensor(ids, torch::kLong));
      shard.push_back(chained_teacher_points(teacher, schedule, first, all_actions.narrow(0, b, m), ids, spec,
                                             tokenizer));
      if (progress) progress->advance(m);
    }
    auto shard_points = torch::cat(shard).contiguous();
    save_safetensors(file, {{"points", shard_points}}, {{"trajectories", shard_meta.dump()}});
    return shard_points;
  };
  const auto shard_file = [&](int64_t k) {
    char name[40];  // room for any long long: GCC checks the bound
    std::snprintf(name, sizeof(name), "shard-%05lld.safetensors", static_cast<long long>(k));
    return dir / name;
  };
  const auto shard_meta_of = [&](int64_t k) {
    const int64_t begin = k * spec.shard_clips, count = std::min(spec.shard_clips, n - begin);
    nlohmann::json shard_meta = meta;
    shard_meta["clips"] = {begin, begin + count};
    return shard_meta;
  };
  const auto cached = [&](const fs::path& file, const nlohmann::json& shard_meta) {
    if (!fs::exists(file)) return false;
    auto f = SafetensorsFile::open(file);
    const auto it = f.metadata().find("trajectories");
    return it != f.metadata().end() && nlohmann::json::parse(it->second) == shard_meta;
  };
  if (group.active()) {
    for (int64_t k = group.rank(); k < shards; k += group.world())
      if (!cached(shard_file(k), shard_meta_of(k))) build_shard(k, shard_file(k), shard_meta_of(k), nullptr);
    group.wait_for_all("the teacher trajectories");
  }
  Progress progress("teacher trajectories", n, "clips");
  for (int64_t k = 0; k < shards; ++k) {
    const int64_t begin = k * spec.shard_clips, count = std::min(spec.shard_clips, n - begin);
    const auto file = shard_file(k);
    const auto shard_meta = shard_meta_of(k);
    if (cached(file, shard_meta)) {
      points.push_back(SafetensorsFile::open(file).tensor("points", true));
      progress.advance(count);
    } else {
      points.push_back(build_shard(k, file, shard_meta, &progress));
    }
    actions.push_back(all_actions.narrow(0, begin, count));
  }
  progress.finish();
  out.points = torch::cat(points);
  out.actions = torch::cat(actions);
  return out;
}

torch::Tensor warmup_loss(models::ActionDitImpl& student, const torch::Tensor& points,
                          const torch::Tensor& actions, const std::vector<int64_t>& timesteps,
                          int64_t window_frames, torch::Generator generator, int64_t sink_frames) {
  const auto index =
      torch::randint(points.size(1), {points.size(0), points.size(3)}, generator, torch::kLong);
  return warmup_loss_at(student, points, actions, timesteps, window_frames, index, sink_frames);
}

torch::Tensor warmup_loss_at(models::ActionDitImpl& student, const torch::Tensor& points,
                             const torch::Tensor& actions, const std::vector<int64_t>& timesteps,
                             int64_t window_frames, torch::Tensor index, int64_t sink_frames,
                             const torch::Tensor& context_offset) {
  const int64_t B = points.size(0), P = points.size(1), T = points.size(3);
  DOJO_CHECK(static_cast<int64_t>(timesteps.size()) == P, "warmup: one timestep per trajectory point");
  DOJO_CHECK(index.size(0) == B && index.size(1) == T, "warmup: one trajectory point per clip and frame");
  index = index.clone();            // the point of every frame
  index.select(1, 0).fill_(P - 1);  // frame 0: clean
  const auto device = student.parameters().front().device();
  const auto b = torch::arange(B).unsqueeze(1), f = torch::arange(T).unsqueeze(0);
  auto x = points.permute({0, 3, 1, 2, 4, 5})
               .index({b, f, index})  // [B, T, 16, h, w]
               .permute({0, 2, 1, 3, 4})
               .to(device);  // [B, 16, T, h, w]
  const auto sigma = (torch::tensor(timesteps, torch::kFloat64).to(torch::kFloat32) / 1000.0)
                         .index({index})
                         .to(device);                // [B, T]
  auto target = points.select(1, P - 1).to(device);  // [B, 16, T, h, w]
  if (context_offset.defined()) {
    DOJO_CHECK(context_offset.sizes() == x.sizes(), "warmup: one context offset per latent");
    const auto offset = context_offset.to(device);
    x = x + offset;
    target = target + offset;
  }
  const auto& c = student.config;
  const int64_t tokens = (x.size(3) / c.patch_spatial) * (x.size(4) / c.patch_spatial);
  models::DitInputs base;
  base.actions = actions.to(device);
  base.self_attn_mask =
      models::dit_block_causal_mask(T, tokens, 0, window_frames + 1, sink_frames).to(device);
  const auto x0 = infer::student_x0_rf(student, base, x, sigma);  // [B, 16, T, h, w]
  return (x0 - target).narrow(2, 1, T - 1).pow(2).mean();
}

torch::Tensor with_clean_context(torch::Tensor point_index, double share, int64_t points,
                                 torch::Generator& generator) {
  if (share <= 0) return point_index;
  const int64_t B = point_index.size(0), T = point_index.size(1);
  DOJO_CHECK(share <= 1 && T >= 2, "warmup: the clean-context share must be in [0, 1], with 2+ frames");
  const auto chosen = torch::rand({B}, generator) < share;                    // [B]
  const auto frontier = torch::randint(1, T, {B}, generator, torch::kLong);   // [B]
  const auto before = torch::arange(T).unsqueeze(0) < frontier.unsqueeze(1);  // [B, T]
  return point_index.masked_fill(before & chosen.unsqueeze(1), points - 1);
}

torch::Tensor context_noise_offsets(const torch::Tensor& point_index, int64_t points,
                                    at::IntArrayRef latent_shape, double max_level,
                                    torch::Generator& generator) {
  if (max_level <= 0) return {};
  const int64_t B = point_index.size(0), T = point_index.size(1);
  DOJO_CHECK(latent_shape.size() == 3, "warmup: context noise needs the latent's [16, h, w]");
  const auto level = torch::rand({B, 1, 1, 1, 1}, generator) * max_level;  // [B, 1, 1, 1, 1]
  const auto eps =
      torch::randn({B, latent_shape[0], T, latent_shape[1], latent_shape[2]}, generator);  // [B, 16, T, h, w]
  auto clean = point_index.eq(points - 1);                                                 // [B, T]
  clean.select(1, 0).fill_(false);  // frame 0 is the recorded frame, streamed as it is
  return level * eps * clean.to(torch::kFloat32).view({B, 1, T, 1, 1});
}

torch::Tensor draw_trajectories(const MixtureIndex& mixture, int64_t copies, int64_t count,
                                torch::Generator& generator) {
  if (!mixture.weighted()) return torch::randint(mixture.size() * copies, {count}, generator, torch::kLong);
  return mixture.draw(count, generator) +
         mixture.size() * torch::randint(copies, {count}, generator, torch::kLong);
}

DistillStage parse_distill_stage(const std::string& text) {
  if (text == "warmup") return DistillStage::kWarmup;
  if (text == "self-forcing") return DistillStage::kSelfForcing;
  throw Error("unknown distillation stage '" + text + "' (expected warmup or self-forcing)");
}

namespace {

// The student settings recorded in `source` (a checkpoint being resumed, or the warmed-up student
// Self-Forcing starts from) win over the command line's: the network was trained with them. Said
// once when they differ, so a --window that does nothing does not pass unnoticed. Starting
// Self-Forcing from a warm-up (sink_from_asked) takes the attention sink from the command line: the
// warm-up's 4-latent clips stay inside any window of 3 frames or more, where a sink changes nothing.
infer::StudentConfig resumed_student_settings(const nlohmann::json& saved, const infer::StudentConfig& asked,
                                              const std::filesystem::path& source,
                                              bool sink_from_asked = false) {
  auto settings = infer::StudentConfig::from_json(saved, source.string() + "/config.json");
  if (sink_from_asked) {
    settings.sink_frames = asked.sink_frames;
    settings.sink_position = asked.sink_position;
    if (settings.sink_frames > settings.window_frames) {
      LOG_WARN("distill: ", source.string(), " attends to ", settings.window_frames,
               " earlier frames: its attention sink is cut from ", settings.sink_frames, " to fit");
      settings.sink_frames = settings.window_frames;
    }
  }
  if (settings.to_json() != asked.to_json())
    LOG_WARN("distill: ", source.string(), " was trained with student settings ", settings.to_json().dump(),
             "; they are kept (the command line asked for ", asked.to_json().dump(), ")");
  return settings;
}

struct TeacherData {
  nlohmann::json config, action_ranges, fingerprint;
  double shift = 5;
  LatentClips clips;
  std::vector<int64_t> set_sizes;  // clips of each dataset, in the order of `clips`
};

// The job's mixture over the teacher data's datasets (logged when weighted) and its record.
std::pair<MixtureIndex, nlohmann::json> distill_mixture(const DistillJob& job, const TeacherData& data) {
  MixtureIndex mixture(data.set_sizes, job.weights);
  std::vector<std::string> names;
  for (const auto& spec : job.data) names.push_back(spec.dataset.string());
  auto record = mixture.record(names);
  if (mixture.weighted()) LOG_INFO("distill: mixture ", record.dump());
  return {std::move(mixture), std::move(record)};
}

// The teacher's config and the job's clips (frames each), normalised with the teacher's own action
// ranges as its rollouts are; cached as out/<prefix>-<i>.safetensors.
TeacherData teacher_data(const DistillJob& job, int frames, const std::string& prefix) {
  DOJO_CHECK(!job.data.empty(), "distill: no dataset given");
  DOJO_CHECK(!job.teacher.empty(), "distill: --teacher is required");
  TeacherData t;
  t.config = Checkpoint::open(resolve_checkpoint_dir(job.teacher)).config();
  t.shift = t.config.contains("sampler") ? t.config["sampler"].value("shift", 5.0) : 5.0;
  t.action_ranges = t.config.value("actions", nlohmann::json::object());
  // A multi-view teacher's clips are its canvas: the student sees the same views.
  const auto views = data::views_of_config(t.config, job.teacher.string());
  std::vector<LatentClips> sets;
  nlohmann::json data_json = nlohmann::json::array();
  // Rank 0 encodes the latent caches; the other ranks read them once they are written.
  data_parallel().main_first("the latent caches", [&] {
    for (size_t i = 0; i < job.data.size(); ++i) {
      auto spec = job.data[i];
      spec.frames = frames;
      if (views && spec.views.empty()) {
        spec.views = views->cameras;
        spec.view_layout = data::to_string(views->layout);
      }
      const auto slot = data::open_dataset(spec.dataset, spec.open_options())->info().action_slot;
      if (!slot.empty() && t.action_ranges.contains(slot))
        spec.action_stats =
            data::ArrayStats::from_json(t.action_ranges[slot], job.teacher.string() + ": actions." + slot);
      sets.push_back(
          load_or_build_latent_clips(spec, job.out / (prefix + "-" + std::to_string(i) + ".safetensors")));
      t.set_sizes.push_back(sets.back().size());
      data_json.push_back(spec.to_json());
    }
  });
  t.clips = concat_latent_clips(sets);
  t.fingerprint = {{"teacher", checkpoint_fingerprint(job.teacher)}, {"data", data_json}};
  return t;
}

// A resumed run keeps the LoRA setting it was started with; says so when the command line differs.
void warn_if_lora_differs(const models::ActionDitImpl& student, const models::LoraConfig& asked,
                          bool resuming, const std::filesystem::path& ckpt_dir) {
  if (resuming && student.config.lora.to_json() != asked.to_json())
    LOG_WARN("distill: ", ckpt_dir.string(), " was started with LoRA ", student.config.lora.to_json().dump(),
             "; it is kept (the command line asked for ", asked.to_json().dump(), ")");
}

// A network with its own parameters, initialised from a checkpoint (trainers must not share).
models::ActionDit fresh_copy(const std::filesystem::path& checkpoint) {
  return models::load_world_model(checkpoint);
}

// A warm-up from --init continues another student of the same network: the trajectories are the
// teacher's, so the student must have the teacher's architecture (its adapters apart).
void check_init_matches_teacher(const nlohmann::json& init_config, const models::ActionDitImpl& teacher,
                                const std::filesystem::path& init) {
  DOJO_CHECK(init_config.contains("config"), init.string() + "/config.json: no 'config' (not a world model)");
  auto student = models::DitConfig::from_json(init_config.at("config"));
  auto reference = teacher.config;
  student.lora = reference.lora = models::LoraConfig{};
  DOJO_CHECK(student.to_json() == reference.to_json(),
             init.string() + ": --init is not a student of this teacher (another architecture)");
}

double mean_of(const std::deque<double>& values) {
  double sum = 0;
  for (double v : values) sum += v;
  return values.empty() ? 0.0 : sum / static_cast<double>(values.size());
}

DistillResult run_warmup(const DistillJob& job) {
  TimeBudget budget(job.time_budget_s);
  fs::create_directories(job.out);
  const auto ckpt_dir = job.out / "checkpoint";
  // One chunk: the 13-frame clips post-training cached; several: Self-Forcing's longer ones.
  const int chunks = job.trajectories.chunks;
  auto& group = data_parallel();
  const auto shards = BatchShards::plan(job.batch_size, job.accumulate, group, "distill");
  const auto data = teacher_data(job, 1 + 12 * chunks, chunks == 1 ? "latents" : "latents-long");
  std::optional<ScopedThreads> matmul_bound;
  if (job.matmul_threads > 0) matmul_bound.emplace(job.matmul_threads);
  const auto& clips = data.clips;
  const auto& action_ranges = data.action_ranges;
  const auto& fingerprint = data.fingerprint;
  const double shift = data.shift;

  auto teacher = models::load_world_model(job.teacher, job.device);
  // The student starts as the teacher (its weights, its architecture), or as --init's student (a
  // second warm-up on other trajectories); a resumed run from its own.
  const bool resuming = checkpoint_exists(ckpt_dir);
  const bool from_init = !resuming && !job.init.empty();
  if (resuming && !job.init.empty())
    LOG_INFO("distill: ", ckpt_dir.string(), " holds a warm-up in progress: it resumes, --init is not read");
  // A resumed run keeps the architecture and the student settings (window, hops) it was started with;
  // a run from --init its student's.
  const fs::path student_source = resuming ? ckpt_dir : from_init ? job.init : fs::path();
  const auto saved = student_source.empty()
                         ? nlohmann::json()
                         : Checkpoint::open(resolve_checkpoint_dir(student_source)).config();
  const auto settings = saved.contains("student")
                            ? resumed_student_settings(saved["student"], job.student, student_source)
                            : job.student;
  if (from_init) check_init_matches_teacher(saved, *teacher, job.init);  // before the trajectories' minutes
  auto trajectory_spec = job.trajectories;
  trajectory_spec.precision = job.precision;
  models::WanVae tokenizer{nullptr};  // re-encoded anchors: the tokenizer the clips were encoded with
  if (trajectory_spec.reencodes_anchors()) {
    tokenizer = models::load_tokenizer(job.data.front().tokenizer);
    tokenizer->to(job.device);
    tokenizer->eval();
  }
  const auto trajectories =
      load_or_build_trajectories(*teacher, shift, clips, trajectory_spec, fingerprint,
                                 job.out / "trajectories", tokenizer.is_empty() ? nullptr : tokenizer.get());
  const int64_t n = trajectories.size();
  // Trajectory j is clip j % N under copy j / N's actions (N clips; copy 0 its own).
  const int64_t clip_count = clips.size();
  DOJO_CHECK(n % clip_count == 0,
             "distill: " + std::to_string(n) + " trajectories for " + std::to_string(clip_count) + " clips");
  const int64_t copies = n / clip_count;
  const auto drawn = distill_mixture(job, data);
  const auto& mixture = drawn.first;
  const auto& mixture_record = drawn.second;

  // What the trajectories are made of besides teacher and data (their shards check those): a run
  // resumed on other trajectories would continue a student trained on the old ones, so it is refused.
  nlohmann::json trajectory_settings = {{"chunks", job.trajectories.chunks},
                                        {"counterfactual_copies", job.trajectories.counterfactual_copies}};
  if (job.trajectories.reencodes_anchors()) trajectory_settings["anchor"] = "reencoded";
  // The resumed run's trainer state: what its trajectories were, where its student started.
  const auto resumed_extra = resuming ? Checkpoint::open(resolve_checkpoint_dir(ckpt_dir)).trainer_extra()
                                      : nlohmann::json::object();
  if (resuming) {
    const auto before =
        resumed_extra.value("trajectories", nlohmann::json{{"chunks", 1}, {"counterfactual_copies", 0}});
    DOJO_CHECK(before == trajectory_settings,
               ckpt_dir.string() + ": the warm-up was started on trajectories " + before.dump() + ", not " +
                   trajectory_settings.dump() + "; give another --out or remove it to start afresh");
  }
  torch::manual_seed(job.seed);
  models::ActionDit start = from_init ? fresh_copy(job.init) : teacher;
  models::ActionDit student = resuming ? models::ActionDit(models::DitConfig::from_json(saved.at("config")))
                              : job.lora.enabled() ? with_lora_adapters(start, job.lora)
                                                   : start;
  warn_if_lora_differs(*student, job.lora, resuming, ckpt_dir);
  // LoRA distillation trains the adapters alone: the action MLPs already read the actions.
  if (student->config.lora.enabled())
    freeze_all_but_adapters(*student, /*train_action_mlps=*/false, "distill");
  WmTrainer trainer(student, job.options, job.device, job.precision);
  nlohmann::json extras = {
      {"actions", action_ranges}, {"student", settings.to_json()}, {"teacher", fingerprint["teacher"]}};
  if (data.config.contains("views")) extras["views"] = data.config["views"];  // a multi-view teacher's canvas
  trainer.set_config_extras(extras);
  // Sharded before a resume adopts the saved moments: each rank then copies its slice only.
  trainer.apply_zero1(job.zero1);
  if (resuming) {
    trainer.resume(ckpt_dir);
    LOG_INFO("distill: resumed from ", ckpt_dir.string(), " at step ", trainer.steps_done());
  }
  group.check_same("the step to resume from", std::to_string(trainer.steps_done()));

  // A fixed batch of points and frame draws tracks the EMA student without batch noise.
  const int64_t probe = std::min<int64_t>(n, 16);
  const auto probe_idx = torch::linspace(0, static_cast<double>(n - 1), probe).to(torch::kLong);
  const auto probe_points = trajectories.points.index_select(0, probe_idx);
  const auto probe_actions = trajectories.actions.index_select(0, probe_idx);
  const auto fixed_batch_loss = [&] {
    torch::NoGradGuard no_grad;
    AutocastGuard autocast(job.device.type(), job.precision);
    return warmup_loss(*trainer.ema(), probe_points, probe_actions, trajectories.timesteps,
                       settings.window_frames, cpu_generator(job.seed + 777), settings.sink_frames)
        .item<double>();
  };
  DistillResult result;
  result.clips = n;
  result.fixed_batch_loss_start = group.main() ? fixed_batch_loss() : std::nan("");

  LoopOptions loop;
  loop.name = "distill warm-up";
  loop.steps = job.steps;
  if (job.time_budget_s > 0) loop.time_budget_s = std::max(1e-3, job.time_budget_s - budget.elapsed());
  loop.save_every = job.save_every;
  loop.loss_curve = job.out / "loss.csv";
  loop.columns = {"loss", "grad_norm", "lr", "fixed_batch_loss"};
  const int64_t start_step = trainer.steps_done();
  std::deque<double> recent;
  const auto recent_mean = [&] {
    double sum = 0;
    for (double v : recent) sum += v;
    return recent.empty() ? 0.0 : sum / static_cast<double>(recent.size());
  };
  // The trainer state every warm-up checkpoint records (the no-step save as the periodic ones).
  nlohmann::json checkpoint_extra = {{"stage", "warmup"},
                                     {"clips", n},
                                     {"trajectories", trajectory_settings},
                                     {"mixture", mixture_record},
                                     {"clean_context_share", job.clean_context_share},
                                     {"context_noise", job.context_noise}};
  // Where the student started, kept across resumes.
  if (from_init) checkpoint_extra["init"] = job.init.string();
  if (resumed_extra.contains("init")) checkpoint_extra["init"] = resumed_extra["init"];
  const auto run = run_training_loop(
      loop, start_step,
      [&](const LoopStep& info) {
        // The whole step's draws on every rank (they are small), in the order of a plain run; each
        // rank then trains on its rows of the batch, so any split of the batch is the same step.
        auto gen = step_generator(job.seed, info.index);
        const auto idx = draw_trajectories(mixture, copies, job.batch_size, gen);
        const auto pts = trajectories.points.index_select(0, idx),
                   acts = trajectories.actions.index_select(0, idx);
        const auto point_index =
            with_clean_context(torch::randint(pts.size(1), {pts.size(0), pts.size(3)}, gen, torch::kLong),
                               job.clean_context_share, pts.size(1), gen);
        const auto context_offset = context_noise_offsets(
            point_index, pts.size(1), {pts.size(2), pts.size(4), pts.size(5)}, job.context_noise, gen);
        const auto s = trainer.step_loss(
            [&](models::ActionDitImpl& net, int64_t j) {
              const int64_t row = shards.row_offset(j), m = shards.micro_batch;
              AutocastGuard autocast(job.device.type(), job.precision);
              return warmup_loss_at(
                  net, pts.narrow(0, row, m), acts.narrow(0, row, m), trajectories.timesteps,
                  settings.window_frames, point_index.narrow(0, row, m), settings.sink_frames,
                  context_offset.defined() ? context_offset.narrow(0, row, m) : torch::Tensor());
            },
            shards.accumulate);
        if (info.saves) trainer.gather_optimizer_state();  // every rank, before rank 0 saves
        recent.push_back(s.loss);
        if (recent.size() > 20) recent.pop_front();
        if (info.index + 1 - start_step == std::min<int64_t>(20, job.steps - start_step))
          result.first_loss = recent_mean();
        std::ostringstream note;
        note << "loss " << s.loss;
        return StepRecord{
            {s.loss, s.grad_norm, s.lr, info.saves && group.main() ? fixed_batch_loss() : std::nan("")},
            job.batch_size,
            note.str()};
      },
      [&](int64_t, bool) { trainer.save(ckpt_dir, checkpoint_extra); });
  if (run.end_step == run.start_step && !resuming && group.main()) trainer.save(ckpt_dir, checkpoint_extra);
  result.steps = trainer.steps_done();
  result.last_loss = recent_mean();
  if (result.first_loss == 0) result.first_loss = result.last_loss;
  result.fixed_batch_loss_end = group.main() ? fixed_batch_loss() : std::nan("");
  result.seconds = run.seconds;
  const nlohmann::json summary = {{"stage", "warmup"},
                                  {"steps", result.steps},
                                  {"clips", n},
                                  {"mixture", mixture_record},
                                  {"first_loss", result.first_loss},
                                  {"last_loss", result.last_loss},
                                  {"fixed_batch_loss_start", result.fixed_batch_loss_start},
                                  {"fixed_batch_loss_end", result.fixed_batch_loss_end},
                                  {"seconds", result.seconds},
                                  {"student", settings.to_json()},
                                  {"device", job.device.str()},
                                  {"precision", dojo::to_string(job.precision)},
                                  {"options", job.options.to_json()},
                                  {"clean_context_share", job.clean_context_share},
                                  {"context_noise", job.context_noise},
                                  {"zero1", job.zero1 && group.active()},
                                  {"optimizer_moment_mib_per_process",
                                   static_cast<double>(trainer.optimizer_moment_bytes()) / (1 << 20)}};
  if (group.main()) write_file_atomic(job.out / "distill_summary.json", summary.dump(2) + "\n");
  return result;
}

DistillResult run_self_forcing(const DistillJob& job) {
  const auto& sf = job.self_forcing;
  DOJO_CHECK(sf.min_frames > sf.loss_frames && sf.max_frames >= sf.min_frames && sf.loss_frames >= 1,
             "self-forcing: need 1 <= loss_frames < min_frames <= max_frames");
  DOJO_CHECK(sf.critic_steps >= 1, "self-forcing: --critic-steps must be >= 1 (the critic must learn)");
  DOJO_CHECK(sf.counterfactual_share >= 0 && sf.counterfactual_share <= 1,
             "self-forcing: --counterfactual-share must be in [0, 1]");
  TimeBudget budget(job.time_budget_s);
  fs::create_directories(job.out);
  const auto ckpt_dir = job.out / "checkpoint", critic_dir = job.out / "critic";
  auto& group = data_parallel();
  const auto shards = BatchShards::plan(job.batch_size, job.accumulate, group, "distill");
  const auto data = teacher_data(job, static_cast<int>(1 + 4 * (sf.max_frames - 1)), "latents-long");
  std::optional<ScopedThreads> matmul_bound;
  if (job.matmul_threads > 0) matmul_bound.emplace(job.matmul_threads);
  const auto& clips = data.clips;  // latents [N, 16, max_frames, h, w], actions [N, 4 (max_frames − 1), 384]
  const int64_t n = clips.size();
  DOJO_CHECK(sf.counterfactual_share == 0 || n >= 2,
             "self-forcing: --counterfactual-share drives rollouts with another clip's actions: it needs at "
             "least 2 clips, got " +
                 std::to_string(n));
  const auto drawn = distill_mixture(job, data);
  const auto& mixture = drawn.first;
  const auto& mixture_record = drawn.second;

  const bool resuming = checkpoint_exists(ckpt_dir) && checkpoint_exists(critic_dir);
  DOJO_CHECK(resuming || !job.init.empty(),
             "distill --stage self-forcing needs --init (the warmed-up student)");
  const auto student_source = resuming ? ckpt_dir : job.init;
  const auto student_config_json = Checkpoint::open(resolve_checkpoint_dir(student_source)).config();
  const auto student =
      student_config_json.contains("student")
          ? resumed_student_settings(student_config_json["student"], job.student, student_source,
                                     /*sink_from_asked=*/!resuming)
          : job.student;
  auto teacher = models::load_world_model(job.teacher, job.device);
  for (auto& p : teacher->parameters()) p.set_requires_grad(false);
  torch::manual_seed(job.seed);
  WmTrainOptions gen_options, critic_options;
  gen_options.lr = sf.generator_lr;
  critic_options.lr = sf.critic_lr;
  for (auto* o : {&gen_options, &critic_options}) {
    o->weight_decay = sf.weight_decay;
    o->grad_clip = sf.grad_clip;
    o->warmup_steps = 0;  // constant, as released
    o->flow.shift = data.shift;
  }
  // A resumed LoRA student is rebuilt from its config (adapters apart) for the trainer to load; a
  // fresh one gets new adapters on the warmed-up student (whose own adapters, if any, are folded in).
  const auto saved_config = models::DitConfig::from_json(student_config_json.at("config"));
  models::ActionDit student_net = resuming && saved_config.lora.enabled() ? models::ActionDit(saved_config)
                                  : job.lora.enabled()
                                      ? with_lora_adapters(fresh_copy(student_source), job.lora)
                                      : fresh_copy(student_source);
  warn_if_lora_differs(*student_net, job.lora, resuming, ckpt_dir);
  if (student_net->config.lora.enabled())
    freeze_all_but_adapters(*student_net, /*train_action_mlps=*/false, "distill");
  WmTrainer generator(student_net, gen_options, job.device, job.precision);
  // The critic starts as the teacher (the fake score equals the real one before any student sample).
  WmTrainer critic(fresh_copy(resuming ? critic_dir : job.teacher), critic_options, job.device,
                   job.precision);
  nlohmann::json generator_extras = {{"actions", data.action_ranges},
                                     {"student", student.to_json()},
                                     {"teacher", data.fingerprint["teacher"]}},
                 critic_extras = {{"actions", data.action_ranges}};
  if (data.config.contains("views"))
    generator_extras["views"] = critic_extras["views"] = data.config["views"];
  generator.set_config_extras(generator_extras);
  critic.set_config_extras(critic_extras);
  generator.apply_zero1(job.zero1);
  critic.apply_zero1(job.zero1);
  if (resuming) {
    // Both are saved at the same iterations; a crash between the two saves leaves them apart.
    const auto iterations = [](const fs::path& dir) {
      return Checkpoint::open(resolve_checkpoint_dir(dir)).trainer_extra().value("iterations", int64_t{-1});
    };
    DOJO_CHECK(
        iterations(ckpt_dir) == iterations(critic_dir),
        job.out.string() + ": the student and critic checkpoints were saved at different iterations (" +
            std::to_string(iterations(ckpt_dir)) + " vs " + std::to_string(iterations(critic_dir)) +
            "); remove " + critic_dir.string() + " and " + ckpt_dir.string() + " to restart the stage");
    generator.resume(ckpt_dir);
    critic.resume(critic_dir);
    LOG_INFO("distill: resumed self-forcing at iteration ", generator.steps_done() + critic.steps_done());
  }
  group.check_same("the iteration to resume from",
                   std::to_string(generator.steps_done() + critic.steps_done()));

  // Fixed clips: the EMA student's full-length rollouts against the clips' own latents.
  const int64_t probe = std::min<int64_t>(n, 4);
  const auto probe_idx = torch::linspace(0, static_cast<double>(n - 1), probe).to(torch::kLong);
  const auto fixed_batch_loss = [&] {
    torch::NoGradGuard no_grad;
    AutocastGuard autocast(job.device.type(), job.precision);
    const auto x = clips.latents.index_select(0, probe_idx).to(job.device);
    auto g = cpu_generator(job.seed + 4242);
    const auto noise = torch::randn(x.sizes(), g).to(job.device);
    const auto rolled = student_rollout(*generator.ema(), student, x.narrow(2, 0, 1),
                                        clips.actions.index_select(0, probe_idx).to(job.device), noise,
                                        student.steps - 1, x.size(2));
    return (rolled - x).narrow(2, 1, x.size(2) - 1).pow(2).mean().item<double>();
  };
  DistillResult result;
  result.clips = n;
  result.fixed_batch_loss_start = group.main() ? fixed_batch_loss() : std::nan("");

  LoopOptions loop;
  loop.name = "distill self-forcing";
  loop.steps = job.steps;
  if (job.time_budget_s > 0) loop.time_budget_s = std::max(1e-3, job.time_budget_s - budget.elapsed());
  loop.save_every = job.save_every;
  loop.loss_curve = job.out / "loss.csv";
  loop.columns = {"generator_loss", "critic_loss", "grad_norm",
                  "exit_hop",       "frames",      "fixed_batch_latent_mse"};
  const int64_t start = generator.steps_done() + critic.steps_done();
  std::deque<double> recent_generator, recent_critic;
  const auto run = run_training_loop(
      loop, start,
      [&](const LoopStep& info) {
        auto g = step_generator(job.seed, info.index);
        const auto idx = mixture.draw(job.batch_size, g);  // unweighted: randint(n), as before weights
        const int exit_hop = static_cast<int>(torch::randint(student.steps, {1}, g).item<int64_t>());
        const int64_t frames = torch::randint(sf.min_frames, sf.max_frames + 1, {1}, g).item<int64_t>();
        const auto x = clips.latents.index_select(0, idx).narrow(2, 0, frames);  // [B, 16, frames, h, w]
        auto action_idx = idx;
        if (sf.counterfactual_share > 0) {  // some rollouts driven by another clip's actions
          const auto other = (idx + torch::randint(1, n, {job.batch_size}, g, torch::kLong)) % n;
          action_idx = torch::where(torch::rand({job.batch_size}, g).lt(sf.counterfactual_share), other, idx);
        }
        const auto acts = clips.actions.index_select(0, action_idx).narrow(1, 0, 4 * (frames - 1));
        const auto noise = torch::randn(x.sizes(), g);
        const int64_t L = sf.loss_frames, first_scored = frames - L;
        const auto u = torch::rand({job.batch_size}, g);
        const auto sigma = sf.shift * u / (1 + (sf.shift - 1) * u);  // [B]
        const auto window_noise = torch::randn({x.size(0), x.size(1), 1 + L, x.size(3), x.size(4)}, g);
        const auto window_actions = acts.narrow(1, 4 * (first_scored - 1), 4 * L);
        const bool generator_phase = info.index % (sf.critic_steps + 1) == 0;
        // Every rank drew the whole step above (in a plain run's order, on the CPU) and runs its
        // rows of it where the networks are.
        const int64_t m = shards.micro_batch;
        const auto rows = [&](const torch::Tensor& t, int64_t j) {
          return t.narrow(0, shards.row_offset(j), m).to(job.device);
        };
        WmStepStats s;
        if (generator_phase) {
          s = generator.step_loss(
              [&](models::ActionDitImpl& net, int64_t j) {
                AutocastGuard autocast(job.device.type(), job.precision);  // the forward passes alone
                const auto rolled = student_rollout(net, student, rows(x, j).narrow(2, 0, 1), rows(acts, j),
                                                    rows(noise, j), exit_hop, first_scored);
                return dmd_generator_loss(*teacher, *critic.net(), rolled.narrow(2, first_scored - 1, 1 + L),
                                          rows(window_actions, j), rows(sigma, j), rows(window_noise, j));
              },
              shards.accumulate);
          recent_generator.push_back(s.loss);
          if (recent_generator.size() > 10) recent_generator.pop_front();
        } else {
          s = critic.step_loss(
              [&](models::ActionDitImpl& net, int64_t j) {
                AutocastGuard autocast(job.device.type(), job.precision);
                torch::Tensor rolled;
                {
                  torch::NoGradGuard no_grad;
                  rolled = student_rollout(*generator.net(), student, rows(x, j).narrow(2, 0, 1),
                                           rows(acts, j), rows(noise, j), exit_hop, frames);
                }
                return critic_loss(net, rolled.narrow(2, first_scored - 1, 1 + L), rows(window_actions, j),
                                   rows(sigma, j), rows(window_noise, j));
              },
              shards.accumulate);
          recent_critic.push_back(s.loss);
          if (recent_critic.size() > 40) recent_critic.pop_front();
        }
        if (info.saves) {  // every rank, before rank 0 saves
          generator.gather_optimizer_state();
          critic.gather_optimizer_state();
        }
        std::ostringstream note;
        note << "generator " << mean_of(recent_generator) << " critic " << mean_of(recent_critic);
        const double nan = std::nan("");
        return StepRecord{{generator_phase ? s.loss : nan, generator_phase ? nan : s.loss, s.grad_norm,
                           static_cast<double>(exit_hop), static_cast<double>(frames),
                           info.saves && group.main() ? fixed_batch_loss() : nan},
                          job.batch_size,
                          note.str()};
      },
      [&](int64_t iterations, bool) {
        critic.save(critic_dir, {{"stage", "self-forcing critic"}, {"iterations", iterations}});
        generator.save(ckpt_dir, {{"stage", "self-forcing"},
                                  {"iterations", iterations},
                                  {"clips", n},
                                  {"mixture", mixture_record}});
      });
  result.steps = generator.steps_done() + critic.steps_done();
  result.first_loss = result.last_loss = mean_of(recent_generator);
  result.fixed_batch_loss_end = group.main() ? fixed_batch_loss() : std::nan("");
  result.seconds = run.seconds;
  const nlohmann::json summary = {
      {"stage", "self-forcing"},
      {"iterations", result.steps},
      {"generator_updates", generator.steps_done()},
      {"critic_updates", critic.steps_done()},
      {"clips", n},
      {"mixture", mixture_record},
      {"generator_loss", mean_of(recent_generator)},
      {"critic_loss", mean_of(recent_critic)},
      {"fixed_batch_latent_mse_start", result.fixed_batch_loss_start},
      {"fixed_batch_latent_mse_end", result.fixed_batch_loss_end},
      {"seconds", result.seconds},
      {"student", student.to_json()},
      {"device", job.device.str()},
      {"precision", dojo::to_string(job.precision)},
      {"options", sf.to_json()},
      {"zero1", job.zero1 && group.active()},
      {"optimizer_moment_mib_per_process",
       static_cast<double>(generator.optimizer_moment_bytes() + critic.optimizer_moment_bytes()) /
           (1 << 20)}};
  if (group.main()) write_file_atomic(job.out / "distill_summary.json", summary.dump(2) + "\n");
  return result;
}

}  // namespace

DistillResult run_distillation(const DistillJob& job) {
  check_training_precision("distill", job.precision);
  DOJO_CHECK(job.student.sink_frames >= 0 && job.student.sink_frames <= job.student.window_frames,
             "distill: the attention sink (" + std::to_string(job.student.sink_frames) +
                 " frames) must fit in the window (" + std::to_string(job.student.window_frames) + ")");
  return job.stage == DistillStage::kWarmup ? run_warmup(job) : run_self_forcing(job);
}

}  // namespace dojo::train
