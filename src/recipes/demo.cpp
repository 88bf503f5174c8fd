#include "recipes/demo.h"

#include <torch/torch.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <functional>
#include <nlohmann/json.hpp>
#include <optional>

#include "core/atomic_file.h"
#include "core/autocast.h"
#include "core/checkpoint.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/log.h"
#include "core/runtime.h"
#include "core/timing.h"
#include "data/episode_store.h"
#include "eval/keypoint_metrics.h"
#include "eval/wm_eval.h"
#include "infer/stream_stats.h"
#include "infer/streaming.h"
#include "infer/world_model.h"
#include "io/video.h"
#include "models/fast_decoder.h"
#include "models/keypoint_probe.h"
#include "models/lam.h"
#include "models/wan_vae.h"
#include "recipes/demo_report.h"
#include "sim/generate.h"
#include "train/distill.h"
#include "train/fast_decoder_train.h"
#include "train/lam_train.h"
#include "train/latent_cache.h"
#include "train/probe_train.h"
#include "train/tokenizer_train.h"
#include "train/wm_train.h"

namespace fs = std::filesystem;

namespace dojo::recipes {
namespace {

// Seconds per step of each stage on the 2-core reference machine (docs/benchmarks.md), for the
// estimate printed up front; scaled by this machine's matrix-multiply speed.
// What matmul_gflops() below measures on that machine, idle (back-to-back products; `dojo
// bench`'s matmul row, one product per timing, reads 150 there).
constexpr double kReferenceGflops = 280.0;
struct StageCost {
  const char* name;
  double fixed_s, step_s;
};
// Measured on a fresh clone of 6144186 (docs/benchmarks.md, "Action following"); the world-model
// stages' fixed part is building their latent caches, eval's the three splits' rollouts.
constexpr StageCost kCosts[] = {
    {"data", 35, 0},
    {"lam", 5, 0.11},
    {"tokenizer", 5, 0.29},
    {"probe", 5, 0.025},
    {"wm_pretrain", 30, 0.225},
    {"wm_posttrain", 30, 0.225},
    // The student's stages: fixed part (latent caches, teacher trajectories, Wan decoding) and step
    // rate measured idle on 2 cores (docs/benchmarks.md, "The real-time student"); the fast
    // decoder's batch-4 rate is half its measured batch-8 one; eval_student is estimated.
    // 4 chained teacher chunks on 128 clips, 13-latent steps; the 2026-11-27 rates (250 s, 0.6 s)
    // scaled by what this host measured on 2026-11-29: re-encoded anchors 1.5x the trajectories'
    // time, the fused backward kernels 1.6x the step rate.
    {"student_warmup", 310, 0.37},
    {"student_self_forcing", 40, 0.39},  // 0.34 at window 3; the paper's 12 costs ~15 % more
    {"fast_decoder", 39, 0.23},
    {"eval", 135, 0},
    {"eval_student", 65, 0},
    {"eval_reference", 135, 0}};

// This machine's float32 matmul speed (GFLOP/s), from 1024^3 products under the thread layout of
// the matmul-bound stages.
double matmul_gflops(int threads) {
  ScopedThreads matmul_bound(threads);
  const auto a = torch::randn({1024, 1024}), b = torch::randn({1024, 1024});
  (void)torch::mm(a, b);
  const int reps = 10;
  const auto t0 = std::chrono::steady_clock::now();
  for (int i = 0; i < reps; ++i) (void)torch::mm(a, b);
  return reps * 2.0 * 1024 * 1024 * 1024 / seconds_since(t0) / 1e9;
}

// Episodes per evaluation split that get a side-by-side video.
constexpr int kEvalVideos = 2;

// Left in OUT/tokenizer by a tokenizer copied in rather than trained there.
constexpr const char* kCopiedMarker = "copied_from.json";

// The tokenizer checkpoint at `from` (weights and config; no trainer state) as DIR/checkpoint.
// Written beside DIR and renamed into place; a tokenizer trained in DIR earlier is kept as
// DIR.trained rather than deleted.
void copy_tokenizer(const fs::path& from, const fs::path& dir) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(from));
  const std::string model = ckpt.config().value("model", "");
  DOJO_CHECK(model == "wan21_vae", (from / "config.json").string() + ": not a tokenizer (model \"" + model +
                                       "\", expected wan21_vae)");
  (void)models::load_tokenizer(from);  // the weights fit the config
  CheckpointData data;
  data.config = ckpt.config();
  data.model = ckpt.model().tensors(/*copy=*/true);
  const fs::path staging = dir.string() + ".copying";
  fs::remove_all(staging);
  save_checkpoint(staging / "checkpoint", data);
  write_file_atomic(staging / kCopiedMarker, nlohmann::json{{"from", from.string()}}.dump(2) + "\n");
  if (fs::exists(dir) && !fs::exists(dir / kCopiedMarker)) {
    const fs::path kept = dir.string() + ".trained";
    fs::remove_all(kept);
    fs::rename(dir, kept);
    LOG_INFO("demo: the tokenizer trained in ", dir.string(), " is kept as ", kept.string());
  }
  fs::remove_all(dir);
  fs::rename(staging, dir);
}

// A new tokenizer invalidates every model trained on its latents: their checkpoints would resume
// at their last step and train no further, so they go (their stages then run afresh).
void discard_models_on_old_latents(const fs::path& out) {
  for (const char* stage : {"wm_pretrain", "wm_posttrain", "student_warmup", "student", "fast_decoder"})
    if (fs::exists(out / stage)) {
      LOG_INFO("demo: the tokenizer changed; discarding ", (out / stage).string());
      fs::remove_all(out / stage);
    }
}

// `to` as a hard link to `from` (a copy across file systems) unless `to` exists or `from` does not.
void link_if_absent(const fs::path& from, const fs::path& to) {
  if (fs::exists(to) || !fs::exists(from)) return;
  fs::create_directories(to.parent_path());
  std::error_code error;
  fs::create_hard_link(from, to, error);
  if (!error) return;
  const fs::path partial = to.string() + ".partial";  // another file system: copied, then renamed
  fs::copy_file(from, partial, fs::copy_options::overwrite_existing);
  fs::rename(partial, to);
}

// Where a stage computes: every trainer and rollout on the device and precision asked; data
// generation (DojoSim) and a copied tokenizer on the CPU in float32, and they say so.
struct RunsOn {
  std::string device = "cpu", precision = "fp32";
};

// The top-level keys in which two stages' settings differ, for the log ("sampler_steps, probe").
std::string changed_inputs(const nlohmann::json& before, const nlohmann::json& now) {
  std::string keys;
  auto add = [&](const std::string& key) { keys += (keys.empty() ? "" : ", ") + key; };
  for (const auto& [key, value] : now.items())
    if (!before.contains(key) || before[key] != value) add(key);
  for (const auto& [key, value] : before.items())
    if (!now.contains(key)) add(key);
  return keys;
}

// One stage of the demo: its name, the inputs that decide its output (the records of the stages it
// reads included), where it computes, and the paths under OUT it writes.
struct Stage {
  std::string name;
  nlohmann::json settings;
  RunsOn runs_on;
  std::vector<std::string> outputs;
};

// Runs `body` unless OUT/stages/<name>.json records a finished run with the same settings on the
// same device and precision. Returns the record: {"settings", "result", "seconds", "finished"},
// written atomically when the stage ends; its settings carry the seed, device and precision too.
// A run whose settings changed starts from scratch: the stage's outputs (checkpoints, latent
// caches, datasets) are discarded first, so no trainer resumes a model made from other inputs.
// Only a run interrupted under the same settings (OUT/stages/<name>.started.json) resumes.
nlohmann::json run_stage(const fs::path& out, const Stage& stage, uint64_t seed,
                         const std::function<nlohmann::json()>& body) {
  nlohmann::json settings = stage.settings;
  settings["seed"] = seed;
  settings["device"] = stage.runs_on.device;
  settings["precision"] = stage.runs_on.precision;
  const fs::path record = out / "stages" / (stage.name + ".json");
  const fs::path started = out / "stages" / (stage.name + ".started.json");
  if (fs::exists(record)) {
    const auto done = read_json_file(record);
    const auto recorded = done.value("settings", nlohmann::json::object());
    // Never re-used from another device or precision than the stage computes on now, whatever
    // else the record says.
    const std::string ran_on = recorded.value("device", std::string("an unrecorded device")) + "/" +
                               recorded.value("precision", std::string("an unrecorded precision"));
    const std::string runs_on = stage.runs_on.device + "/" + stage.runs_on.precision;
    if (ran_on != runs_on) {
      LOG_INFO("demo: ", stage.name, " ran on ", ran_on, ", runs on ", runs_on, " now; running it again");
    } else if (recorded == settings) {
      LOG_INFO("demo: ", stage.name, " finished earlier (", record.string(), "); re-using it");
      return done;
    } else {
      LOG_INFO("demo: ", stage.name, " ran with other inputs (", changed_inputs(recorded, settings),
               "); running it again");
    }
  }
  const bool resumes = fs::exists(started) && read_json_file(started) == settings;
  if (resumes) {
    LOG_INFO("demo: ", stage.name, " was interrupted; resuming it");
  } else {
    // Only what a record or a started marker says this demo wrote is discarded: a directory of the
    // same name that the demo did not make is the user's, and is refused rather than deleted.
    const bool ours = fs::exists(record) || fs::exists(started);
    for (const auto& output : stage.outputs)
      DOJO_CHECK(ours || !fs::exists(out / output),
                 (out / output).string() + ": exists, but no record in " + (out / "stages").string() +
                     " says the demo wrote it; move it away or give another --out");
    fs::remove(record);  // first: a record must never outlive the outputs it describes
    for (const auto& output : stage.outputs) fs::remove_all(out / output);
    fs::create_directories(started.parent_path());
    write_file_atomic(started, settings.dump(2) + "\n");
  }
  const auto t0 = std::chrono::steady_clock::now();
  const auto result = body();
  const nlohmann::json done = {{"settings", settings},
                               {"result", result},
                               {"seconds", seconds_since(t0)},
                               {"finished", static_cast<int64_t>(std::time(nullptr))}};
  write_file_atomic(record, done.dump(2) + "\n");
  fs::remove(started);
  return done;
}

// The student streaming one held-out episode's first frame and recorded actions (looped) for
// `frames` frames (600 by default; the file and key names say 600 whatever the count) at batch 1
// with the fast decoder: frames/s, step latency and memory.
nlohmann::json time_streaming(const fs::path& out, const fs::path& tokenizer, torch::Device device,
                              Precision precision, int threads, int frames) {
  ScopedThreads matmul_bound(threads);
  infer::StreamingEngine::Options so;
  so.device = device;
  so.precision = precision;
  so.fast_decoder = models::load_fast_decoder(out / "fast_decoder" / "checkpoint");
  auto engine = infer::StreamingEngine::load(out / "student" / "checkpoint", tokenizer, so);
  const auto clip = data::read_episode_clip(
      out / "robot", "val", "", 4, data::parse_action_ranges(engine.action_ranges(), "student actions"));
  io::VideoWriterOptions vo;
  vo.fps = 10;
  io::VideoWriter video((out / "student_600_frames.mp4").string(), vo);  // the long rollout, for the report
  video.write_many(engine.reset(clip.video.narrow(0, 0, 1), 0)[0]);
  infer::StreamStats stats;
  for (int64_t done = 4; done <= frames; done += 4) {
    const int64_t s = (done / 4 - 1) % (clip.actions.size(0) / 4);
    const auto frames_out = engine.step(clip.actions.narrow(0, 4 * s, 4).unsqueeze(0));  // [1, 4, H, W, 3]
    stats.add(engine.last_timings(), frames_out.size(1));
    video.write_many(frames_out[0]);
  }
  const auto summary = stats.summary();
  video.close();
  return {{"frames", stats.frames()},
          {"frames_per_second", summary["steady_frames_per_second"]},
          {"step_ms_p50", summary["steady_step_ms_p50"]},  // after warm-up, like frames_per_second
          {"step_ms_p95", summary["steady_step_ms_p95"]},
          {"rss_mib_frame_100", summary["rss_mib_at_frame_100"]},
          {"rss_mib_frame_600", summary["rss_mib_at_end"]}};
}

}  // namespace

DemoSummary run_demo(const DemoOptions& o) {
  // First, so a CUDA request without CUDA (or fp16, which training rejects) fails before any work.
  const auto device = parse_device(o.device);
  const auto precision = parse_precision(o.precision);
  if (precision == Precision::kFloat16)
    throw UsageError("demo: --precision fp16 cannot train the world model (no loss scaling); use bf16");
  if (!o.reference.empty()) {
    for (const char* part : {"tokenizer", "probe", "wm_posttrain"})
      DOJO_CHECK(fs::exists(o.reference / part / "config.json"),
                 (o.reference / part).string() + ": missing from the reference model set");
  }
  DOJO_CHECK(o.max_clips > 0, "demo: max_clips must be positive");
  DOJO_CHECK(o.eval_chunks > 0 && o.warmup_chunks > 0, "demo: eval and warm-up chunks must be positive");
  // Evaluation rollouts, the warm-up's chained trajectories and the timed stream (4 chunks of a
  // held-out episode) each need this many frames of an episode.
  const int needed_frames = 1 + 12 * std::max({o.eval_chunks, o.warmup_chunks, 4});
  DOJO_CHECK(o.frames >= needed_frames,
             "demo: --frames " + std::to_string(o.frames) +
                 " is too short: the rollouts, the warm-up and the timed stream need " +
                 std::to_string(needed_frames) + " frames an episode");
  DOJO_CHECK(o.stream_frames >= 4 && o.stream_frames % 4 == 0,
             "demo: the student streams 4 frames a step: stream_frames must be a positive multiple of 4");
  if (!o.tokenizer.empty())
    DOJO_CHECK(
        fs::exists(o.tokenizer / "config.json"),
        (o.tokenizer / "config.json").string() + ": missing (--tokenizer names a tokenizer checkpoint)");
  const fs::path out = o.out;
  fs::create_directories(out);
  const auto start = std::chrono::steady_clock::now();
  // Matmul-bound stages (LAM, world model, rollouts) on CPU: one OpenMP thread beside a threaded
  // BLAS unless the caller chose (core/runtime.h says why).
  auto matmul_threads = [&](bool on_cuda) {
    if (on_cuda) return threads();
    return o.matmul_threads > 0 ? o.matmul_threads : matmul_bound_threads();
  };

  // Budgets. Steps by default; with --minutes, the training stages share the time left after
  // data generation in fixed proportions, recomputed from the clock as each stage starts.
  const std::map<std::string, int64_t> steps = {{"lam", o.lam_steps},
                                                {"tokenizer", o.tokenizer_steps},
                                                {"probe", o.probe_steps},
                                                {"wm_pretrain", o.pretrain_steps},
                                                {"wm_posttrain", o.posttrain_steps},
                                                {"student_warmup", o.warmup_steps},
                                                {"student_self_forcing", o.self_forcing_steps},
                                                {"fast_decoder", o.fast_decoder_steps}};
  const std::map<std::string, double> time_share = {
      {"lam", 0.09}, {"tokenizer", 0.36}, {"probe", 0.05}, {"wm_pretrain", 0.22}, {"wm_posttrain", 0.28}};
  const bool trains_tokenizer = o.tokenizer.empty();
  auto stage_minutes = [&](const std::string& name) -> double {
    if (o.minutes <= 0) return 0;
    double later = 0;
    bool after = false;
    for (const char* s : {"lam", "tokenizer", "probe", "wm_pretrain", "wm_posttrain"}) {
      if (s == name) after = true;
      if (after && (trains_tokenizer || std::string(s) != "tokenizer")) later += time_share.at(s);
    }
    const double left = o.minutes * 0.9 - seconds_since(start) / 60.0;  // 10% kept for evaluation
    return std::max(0.05, left * time_share.at(name) / later);
  };
  {
    const double factor = kReferenceGflops / std::max(1.0, matmul_gflops(matmul_threads(/*on_cuda=*/false)));
    double reference_s = 0;
    for (const auto& c : kCosts) {
      if (std::string(c.name) == "eval_reference" && o.reference.empty()) continue;
      if (std::string(c.name) == "tokenizer" && !trains_tokenizer) continue;
      reference_s += c.fixed_s + c.step_s * (steps.count(c.name) ? steps.at(c.name) : 0);
    }
    if (o.minutes > 0)
      LOG_INFO("demo: time budget ", o.minutes, " min (results depend on the machine's speed)");
    else
      LOG_INFO("demo: expected ~", static_cast<int>(std::lround(reference_s * factor / 60)),
               " min on this machine (", static_cast<int>(std::lround(reference_s / 60)),
               " min on the 2-core reference); stages re-used from earlier runs take no time");
  }
  auto budget_settings = [&](const std::string& name) {
    return o.minutes > 0 ? nlohmann::json{{"minutes", o.minutes}} : nlohmann::json{{"steps", steps.at(name)}};
  };
  nlohmann::json stages;
  // Where the stages compute: every trainer and rollout on the device and precision asked; DojoSim
  // and a copied tokenizer on the CPU.
  const RunsOn on_cpu;
  const RunsOn as_asked{device.str(), to_string(precision)};

  // 1. The world.
  LOG_INFO("[1/10] DojoSim: human and robot episodes into ", out.string());
  const nlohmann::json data_settings = {{"episodes", o.episodes},
                                        {"eval_episodes", o.eval_episodes},
                                        {"frames", o.frames},
                                        {"keypoints", true}};
  // DojoSim refuses to add episodes of other options to a dataset: other settings start afresh.
  const std::vector<std::string> data_outputs = {"human",
                                                 "robot",
                                                 "robot_ood_objects",
                                                 "robot_counterfactual",
                                                 "preview_human.mp4",
                                                 "preview_robot.mp4"};
  stages["data"] = run_stage(out, {"data", data_settings, on_cpu, data_outputs}, o.seed, [&] {
    nlohmann::json result;
    auto generate = [&](const std::string& name, const std::string& embodiment, const std::string& split,
                        int episodes, uint64_t seed, double val_fraction = 0) {
      sim::GenerateOptions g;
      g.val_fraction = val_fraction;
      g.embodiment = embodiment;
      g.split = split;
      g.episodes = episodes;
      g.frames = o.frames;
      g.seed = seed;
      g.workers = o.workers;
      const auto s = sim::generate_dataset(out / name, g);
      result[name] = {{"episodes", episodes}, {"seconds", s.seconds}};
      if (!std::isnan(s.mean_success)) result[name]["bin_success"] = s.mean_success;
    };
    generate("human", "human", "train", o.episodes, o.seed);
    // The last eval_episodes robot episodes form the held-out "val" split.
    generate("robot", "robot", "train", o.episodes + o.eval_episodes, o.seed + 1,
             static_cast<double>(o.eval_episodes) / (o.episodes + o.eval_episodes));
    generate("robot_ood_objects", "robot", "ood-objects", o.eval_episodes, o.seed + 2);
    generate("robot_counterfactual", "robot", "counterfactual", o.eval_episodes, o.seed + 3);
    data::write_preview_video(data::EpisodeStore::open(out / "human"), out / "preview_human.mp4", 4, 4);
    data::write_preview_video(data::EpisodeStore::open(out / "robot"), out / "preview_robot.mp4", 4, 4);
    return result;
  });

  // 2. Latent action model on human and robot video (no actions used).
  LOG_INFO("[2/10] LAM: latent actions from video alone");
  const Stage lam_stage{
      "lam", {{"budget", budget_settings("lam")}, {"data", stages["data"]}}, as_asked, {"lam"}};
  stages["lam"] = run_stage(out, lam_stage, o.seed, [&] {
    train::LamTrainJob lam;
    lam.datasets = {{out / "human", 1.0}, {out / "robot", 1.0}};
    lam.out = out / "lam";
    lam.model = models::LamConfig::small();
    lam.options.lr = 3e-4;  // small model, short run: the released 2.5e-5 is for 700 M parameters
    lam.batch_size = 8;
    lam.steps = o.minutes > 0 ? 1000000 : o.lam_steps;
    lam.time_budget_s = stage_minutes("lam") * 60;
    lam.save_every = 100;
    lam.seed = o.seed;
    lam.device = device;
    lam.precision = precision;
    ScopedThreads matmul_bound(matmul_threads(device.is_cuda()));
    const auto s = train::run_lam_training(lam);
    return nlohmann::json{{"mse", s.mse}, {"psnr", s.psnr}};
  });

  // 3. Tokenizer: a trained one copied in as is (the paper, too, takes its VAE pretrained: Wan2.1's),
  // or trained here. Either way it lands in OUT/tokenizer/checkpoint, where the commands that take
  // --demo look for it.
  const fs::path tokenizer = out / "tokenizer" / "checkpoint";
  if (!o.tokenizer.empty()) {
    LOG_INFO("[3/10] tokenizer: ", o.tokenizer.string(),
             " as is (trained beforehand, as the paper's VAE is)");
    const auto from = fs::absolute(o.tokenizer).lexically_normal();
    // Its weights' path, size and time: another tokenizer of the same architecture has the same size.
    const nlohmann::json settings = {{"copied_from", from.string()},
                                     {"checkpoint", checkpoint_fingerprint(from)}};
    // Copied, not computed; a tokenizer trained here earlier is kept (copy_tokenizer), not discarded.
    const Stage tokenizer_stage{"tokenizer", settings, on_cpu, {}};
    stages["tokenizer"] = run_stage(out, tokenizer_stage, o.seed, [&] {
      discard_models_on_old_latents(out);
      copy_tokenizer(from, out / "tokenizer");
      return nlohmann::json{{"copied_from", from.string()}};
    });
  } else {
    LOG_INFO("[3/10] tokenizer: Wan2.1-architecture VAE");
    const Stage tokenizer_stage{"tokenizer",
                                {{"budget", budget_settings("tokenizer")}, {"data", stages["data"]}},
                                as_asked,
                                {"tokenizer"}};
    stages["tokenizer"] = run_stage(out, tokenizer_stage, o.seed, [&] {
      discard_models_on_old_latents(out);
      // A copied tokenizer has no trainer state to resume: training starts afresh.
      if (fs::exists(out / "tokenizer" / kCopiedMarker)) fs::remove_all(out / "tokenizer");
      models::WanVaeConfig cfg;
      cfg.dim = 16;
      // Seeded before the weights are drawn: the LAM stage draws from the global generator as
      // it trains, so without this the tokenizer's initialisation would depend on whether the
      // LAM stage ran in this process or was re-used, and for how many steps.
      torch::manual_seed(o.seed);
      models::WanVae vae(cfg);
      models::init_frame_by_frame(vae);  // image phase first; a resumed run loads over this
      data::ClipConfig clip;
      // 9 frames = 3 latent frames: the first chunk and one steady-state chunk that decodes
      // from the causal caches of the one before (trained on 5 frames only, latent frames >= 2
      // of the world model's 13-frame clips decoded to flat colour).
      clip.num_frames = 9;
      clip.strides = {1, 2};
      clip.height = clip.width = 64;
      const auto batches =
          train::tokenizer_batches({{out / "human", "all"}, {out / "robot", "train"}}, clip,
                                   /*clip_batch=*/4, /*image_batch=*/8, /*workers=*/1, o.seed);
      train::TokenizerTrainOptions t = train::recommended_tokenizer_options();
      t.warmup_steps = 20;
      t.steps = o.minutes > 0 ? 1000000 : o.tokenizer_steps;
      t.time_budget_s = stage_minutes("tokenizer") * 60;
      t.save_every = 100;
      t.checkpoint_dir = tokenizer;
      t.loss_curve = out / "tokenizer" / "loss.csv";
      t.stats_batches = 8;
      t.next_image_batch = batches.images;
      t.device = device;
      t.precision = precision;
      fs::create_directories(out / "tokenizer");
      torch::manual_seed(o.seed);
      const auto r = train::train_tokenizer(vae, batches.clips, t);
      return nlohmann::json{
          {"steps", r.steps_done}, {"recon_first", r.first_loss}, {"recon_last", r.last_loss}};
    });
  }

  // 4. Keypoint probe: where the arm and the hand are, to score rollouts by.
  LOG_INFO("[4/10] keypoint probe: finds the arm and the hand in a frame");
  const fs::path probe_dir = out / "probe" / "checkpoint";
  const Stage probe_stage{
      "probe", {{"budget", budget_settings("probe")}, {"data", stages["data"]}}, as_asked, {"probe"}};
  stages["probe"] = run_stage(out, probe_stage, o.seed, [&] {
    train::ProbeTrainJob job;
    job.datasets = {out / "robot", out / "human"};
    job.out = out / "probe";
    job.steps = o.minutes > 0 ? 1000000 : o.probe_steps;
    job.time_budget_s = stage_minutes("probe") * 60;
    job.seed = o.seed;
    job.device = device;
    job.precision = precision;
    const auto r = train::run_probe_training(job);
    auto probe = models::load_keypoint_probe(probe_dir);
    const auto accuracy = eval::probe_accuracy(probe, {out / "robot"}, "val");
    return nlohmann::json{{"steps", r.steps}, {"loss", r.loss}, {"heldout_robot", accuracy.to_json()}};
  });

  // 5-6. World model: pretrain on human video with latent actions, post-train on robot actions.
  auto wm_job = [&](train::WmStage stage, const fs::path& dataset, const std::string& split,
                    train::ActionMode mode, const std::string& name) {
    train::WmTrainJob job;
    job.stage = stage;
    train::LatentCacheSpec spec;
    spec.dataset = dataset;
    spec.split = split;
    spec.tokenizer = tokenizer;
    spec.lam = out / "lam" / "checkpoint";
    spec.mode = mode;
    // Encoding is the slow part of caching (one 13-frame clip at a time, as the release does):
    // windows every 4 frames at strides 1 and 2, at most max_clips of them, evenly spread.
    spec.hop = 4;
    spec.max_clips = o.max_clips;
    job.data = {spec};
    job.out = out / name;
    if (stage == train::WmStage::kPosttrain) {
      job.init = out / "wm_pretrain" / "checkpoint";
      job.options.condition_noise = o.posttrain_condition_noise;
    }
    job.model = models::DitConfig::small();
    job.options.lr = 3e-4;  // small network, few thousand steps
    job.options.grad_clip = 1.0;
    job.options.warmup_steps = 50;
    job.batch_size = 8;
    job.steps = o.minutes > 0 ? 1000000 : steps.at(name);
    job.time_budget_s = stage_minutes(name) * 60;
    job.save_every = 100;
    job.seed = o.seed;
    job.device = device;
    job.precision = precision;
    job.matmul_threads = matmul_threads(device.is_cuda());  // once its latent cache is encoded
    const auto r = train::run_wm_training(job);
    return nlohmann::json{{"steps", r.steps},
                          {"loss_first", r.first_loss},
                          {"loss_last", r.last_loss},
                          {"clips_per_second", r.clips_per_second},
                          {"gflops", r.gflops}};
  };
  LOG_INFO("[5/10] world model pretraining on human video with latent actions");
  const Stage wm_pretrain_stage{"wm_pretrain",
                                {{"budget", budget_settings("wm_pretrain")},
                                 {"lam", stages["lam"]},
                                 {"tokenizer", stages["tokenizer"]},
                                 {"max_clips", o.max_clips}},
                                as_asked,
                                {"wm_pretrain"}};
  stages["wm_pretrain"] = run_stage(out, wm_pretrain_stage, o.seed, [&] {
    return wm_job(train::WmStage::kPretrain, out / "human", "all", train::ActionMode::kLatent, "wm_pretrain");
  });
  LOG_INFO("[6/10] world model post-training on robot actions");
  const Stage wm_posttrain_stage{"wm_posttrain",
                                 {{"budget", budget_settings("wm_posttrain")},
                                  {"init", stages["wm_pretrain"]},
                                  {"condition_noise", o.posttrain_condition_noise},
                                  {"max_clips", o.max_clips}},
                                 as_asked,
                                 {"wm_posttrain"}};
  stages["wm_posttrain"] = run_stage(out, wm_posttrain_stage, o.seed, [&] {
    return wm_job(train::WmStage::kPosttrain, out / "robot", "train", train::ActionMode::kDataset,
                  "wm_posttrain");
  });

  // 7. The real-time student, distilled from the post-trained model, and its fast decoder. Step
  // budgets even under --minutes (they are short).
  LOG_INFO("[7/10] real-time student: ", o.self_forcing_steps > 0 ? "warm-up and Self-Forcing" : "warm-up",
           " from the post-trained world model");
  // The paper's window (released: 3): within 0.1 dB of the teacher on 49-frame rollouts where 3
  // left 2.2 dB (docs/benchmarks.md, "The paper's window").
  const int window_frames = 12;
  // The real first frame kept in view past the window: on 145-frame rollouts it lifted the
  // window-12 student from 2.1 dB under the teacher to above it (docs/benchmarks.md, "An attention
  // sink").
  const int sink_frames = 1;
  const Stage student_stage{"student",
                            {{"warmup_steps", o.warmup_steps},
                             {"warmup_chunks", o.warmup_chunks},
                             {"self_forcing_steps", o.self_forcing_steps},
                             {"warmup_reencoded_anchors", o.warmup_reencoded_anchors},
                             {"warmup_clean_context_share", o.warmup_clean_context_share},
                             {"window_frames", window_frames},
                             {"sink_frames", sink_frames},
                             {"max_clips", o.max_clips},
                             {"teacher", stages["wm_posttrain"]}},
                            as_asked,
                            {"student_warmup", "student"}};
  stages["student"] = run_stage(out, student_stage, o.seed, [&] {
    train::DistillJob job;
    train::LatentCacheSpec spec;
    spec.dataset = out / "robot";
    spec.tokenizer = tokenizer;
    spec.hop = 4;
    spec.max_clips = o.max_clips;
    job.data = {spec};
    job.teacher = out / "wm_posttrain" / "checkpoint";
    job.student.window_frames = window_frames;
    job.student.sink_frames = sink_frames;
    const bool self_forcing = o.self_forcing_steps > 0;
    job.out = out / (self_forcing ? "student_warmup" : "student");
    // With one chunk its 13-frame latent cache is post-training's (the same clips, tokenizer and
    // action ranges): linked rather than encoded again. The cache checks its spec, so a mismatch
    // only re-encodes.
    if (o.warmup_chunks == 1)
      link_if_absent(out / "wm_posttrain" / "latents-0.safetensors", job.out / "latents-0.safetensors");
    job.trajectories.chunks = o.warmup_chunks;
    job.trajectories.seed = o.seed;
    job.trajectories.reencode_anchor = o.warmup_reencoded_anchors;
    job.clean_context_share = o.warmup_clean_context_share;
    // Trajectories of 13 latents cost ~3x the 4-latent ones a step: half the batch.
    if (o.warmup_chunks > 1) job.batch_size = 4;
    job.steps = o.warmup_steps;
    job.save_every = 100;
    job.seed = o.seed;
    job.device = device;
    job.precision = precision;
    job.matmul_threads = matmul_threads(device.is_cuda());  // once the latent caches are encoded
    const auto warmup = train::run_distillation(job);
    nlohmann::json result = {
        {"warmup_steps", warmup.steps},
        {"warmup_fixed_batch_loss", {warmup.fixed_batch_loss_start, warmup.fixed_batch_loss_end}},
        {"self_forcing_iterations", 0}};
    if (!self_forcing) return result;
    job.stage = train::DistillStage::kSelfForcing;
    job.init = out / "student_warmup" / "checkpoint";
    job.out = out / "student";
    // The 49-frame clips of a chained warm-up are Self-Forcing's own: linked, not encoded again.
    link_if_absent(out / "student_warmup" / "latents-long-0.safetensors",
                   job.out / "latents-long-0.safetensors");
    job.steps = o.self_forcing_steps;
    job.batch_size = 2;
    job.save_every = 50;
    const auto sf = train::run_distillation(job);
    result["self_forcing_iterations"] = sf.steps;
    result["rollout_latent_mse"] = {sf.fixed_batch_loss_start, sf.fixed_batch_loss_end};
    return result;
  });
  LOG_INFO("[8/10] fast streaming decoder distilled from the tokenizer");
  // Its clips come from the robot data, whichever way the tokenizer came (a copied one records none).
  const Stage fast_decoder_stage{"fast_decoder",
                                 {{"steps", o.fast_decoder_steps},
                                  {"tokenizer", stages["tokenizer"]},
                                  {"data", stages["data"]},
                                  {"max_clips", o.max_clips}},
                                 as_asked,
                                 {"fast_decoder"}};
  stages["fast_decoder"] = run_stage(out, fast_decoder_stage, o.seed, [&] {
    train::FastDecoderJob job;
    train::LatentCacheSpec spec;
    spec.dataset = out / "robot";
    spec.tokenizer = tokenizer;
    spec.hop = 4;
    spec.strides = {1};
    spec.max_clips = o.max_clips;
    job.data = {spec};
    job.out = out / "fast_decoder";
    job.batch_size = 4;  // half the default: the demo's time budget
    job.steps = o.fast_decoder_steps;
    job.seed = o.seed;
    job.device = device;
    job.precision = precision;
    // Convolutions (the Wan encoder and decoder, the fast decoder): every thread, unlike the
    // matmul-bound stages. 1.54x the steps/s of one thread (docs/benchmarks.md).
    const auto r = train::run_fast_decoder_training(job);
    return nlohmann::json{{"steps", r.steps}, {"heldout_psnr_vs_wan", r.heldout_psnr}};
  });

  // 9. Rollouts and evaluation, of the demo's models and of the reference set.
  LOG_INFO("[9/10] rollouts: ", 1 + 12 * o.eval_chunks, " frames (", o.eval_chunks, " chunks, ",
           o.eval_chunks - 1,
           " resets) on held-out, out-of-distribution and counterfactual robot episodes, with true, shuffled "
           "and zero actions");
  auto evaluate = [&](const fs::path& wm, const fs::path& tok, const fs::path& probe_ckpt,
                      const fs::path& videos, bool student = false) {
    auto model = infer::WorldModel::load(wm, tok, device, precision);
    std::optional<infer::StreamingEngine> engine;
    if (student) {
      infer::StreamingEngine::Options so;
      so.device = device;
      so.precision = precision;
      so.fast_decoder = models::load_fast_decoder(out / "fast_decoder" / "checkpoint");
      engine.emplace(infer::StreamingEngine::load(wm, tok, so));
    }
    auto probe = models::load_keypoint_probe(probe_ckpt);
    eval::WmEvalOptions eo;
    eo.max_episodes = o.eval_episodes;
    eo.chunks = o.eval_chunks;
    eo.sampler = model.trained_sampler();
    eo.sampler.steps = o.sampler_steps;
    eo.seed = o.seed;
    eo.video_dir = videos;
    eo.videos = kEvalVideos;
    eo.probe = &probe;
    eo.action_sensitivity = o.eval_episodes >= 2;  // shuffling needs another episode's actions
    if (engine) eo.student = &*engine;
    // DiT sampling is matmul-bound: 31.0 generated frames/s with one OpenMP thread, 12.6 with two.
    ScopedThreads matmul_bound(matmul_threads(device.is_cuda()));
    nlohmann::json results = nlohmann::json::array();
    for (const auto& [dir, split, name] : std::vector<std::tuple<std::string, std::string, std::string>>{
             {"robot", "val", "val"},
             {"robot_ood_objects", "all", "ood-objects"},
             {"robot_counterfactual", "all", "counterfactual"}}) {
      auto r = eval::evaluate_world_model(model, out / dir, split, eo);
      r.split = name;
      results.push_back(r.to_json());
    }
    return results;
  };
  // What an evaluation's numbers depend on beside its models, probe and data (the held-out splits,
  // in the data record the models' records embed), the seed, the device and the precision. The
  // student streams its own few steps: the teacher's sampler steps are not among its inputs.
  auto eval_settings = [&](bool sampler) {
    nlohmann::json e = {{"episodes", o.eval_episodes},
                        {"chunks", o.eval_chunks},
                        {"videos", kEvalVideos},
                        {"action_sensitivity", o.eval_episodes >= 2}};
    if (sampler) e["sampler_steps"] = o.sampler_steps;
    return e;
  };
  const Stage eval_stage{
      "eval",
      {{"wm", stages["wm_posttrain"]}, {"probe", stages["probe"]}, {"eval", eval_settings(/*sampler=*/true)}},
      as_asked,
      {"rollouts"}};
  stages["eval"] = run_stage(out, eval_stage, o.seed, [&] {
    return evaluate(out / "wm_posttrain" / "checkpoint", tokenizer, probe_dir, out / "rollouts");
  });
  const Stage eval_student_stage{"eval_student",
                                 {{"student", stages["student"]},
                                  {"fast_decoder", stages["fast_decoder"]},
                                  {"probe", stages["probe"]},
                                  {"eval", eval_settings(/*sampler=*/false)},
                                  {"stream_frames", o.stream_frames}},
                                 as_asked,
                                 {"rollouts_student", "student_600_frames.mp4"}};
  stages["eval_student"] = run_stage(out, eval_student_stage, o.seed, [&] {
    auto result = nlohmann::json{{"splits", evaluate(out / "student" / "checkpoint", tokenizer, probe_dir,
                                                     out / "rollouts_student", /*student=*/true)}};
    result["streaming"] =
        time_streaming(out, tokenizer, device, precision, matmul_threads(device.is_cuda()), o.stream_frames);
    return result;
  });
  if (!o.reference.empty()) {
    const auto ref = fs::absolute(o.reference).lexically_normal();
    // The reference set by its weights (path, size and time of each), not only its path.
    const nlohmann::json reference = {{"path", ref.string()},
                                      {"tokenizer", checkpoint_fingerprint(ref / "tokenizer")},
                                      {"probe", checkpoint_fingerprint(ref / "probe")},
                                      {"wm", checkpoint_fingerprint(ref / "wm_posttrain")}};
    const Stage eval_reference_stage{
        "eval_reference",
        {{"reference", reference}, {"data", stages["data"]}, {"eval", eval_settings(/*sampler=*/true)}},
        as_asked,
        {"rollouts_reference"}};
    stages["eval_reference"] = run_stage(out, eval_reference_stage, o.seed, [&] {
      return evaluate(ref / "wm_posttrain", ref / "tokenizer", ref / "probe", out / "rollouts_reference");
    });
  }

  // 10. Report.
  LOG_INFO("[10/10] report: ", (out / "report.html").string());
  stages["seconds"] = seconds_since(start);
  stages["device"] = device.str();
  stages["precision"] = to_string(precision);
  write_file_atomic(out / "demo.json", stages.dump(2) + "\n");
  DemoSummary summary;
  summary.report = out / "report.html";
  summary.eval_table = write_demo_report(out, stages);
  summary.seconds = seconds_since(start);
  return summary;
}

}  // namespace dojo::recipes
