// `dojo distill` and `dojo wm stream` end to end on the reference teacher: a short warm-up makes a
// student checkpoint that `wm stream` and `eval --student` run; bad action lines get one-line
// errors naming the line.
#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "core/safetensors.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo {
namespace {

void write_lines(const std::filesystem::path& file, const std::vector<std::string>& lines) {
  std::ofstream out(file);
  for (const auto& l : lines) out << l << "\n";
}

std::string rows(int n, int width, double value) {
  nlohmann::json chunk = nlohmann::json::array();
  for (int r = 0; r < n; ++r)
    chunk.push_back(std::vector<double>(static_cast<size_t>(width), value * (r + 1)));
  return chunk.dump();
}

TEST(StreamCli, DistillThenStreamAndEvaluateTheStudent) {
  test::OneThread one;
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 2;
  g.frames = 52;
  g.size = 64;
  test::write_synthetic_dataset(tmp / "robot", g);
  const auto data = (tmp / "robot").string();
  const auto out = tmp / "distill";
  auto r = test::run_dojo("--threads 1 distill --data " + data +
                          " --split all --max-clips 4 --teacher-steps 4 --steps 3 "
                          "--batch 2 --clean-context-share 0.5 --context-noise 0.25 --out " +
                          out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto warmup = nlohmann::json::parse(test::read_file(out / "distill_summary.json"));
  EXPECT_EQ(warmup.at("clean_context_share"), 0.5);
  EXPECT_EQ(warmup.at("context_noise"), 0.25);
  const auto config = nlohmann::json::parse(test::read_file(out / "checkpoint" / "config.json"));
  EXPECT_EQ(config.at("student").at("window_frames"), 12);  // the paper's, by default
  EXPECT_EQ(config.at("student").at("sink_frames"), 1);     // the first frame kept in view
  EXPECT_TRUE(config.at("actions").contains("dojosim_robot")) << "the teacher's action ranges travel on";
  EXPECT_TRUE(std::filesystem::exists(out / "trajectories" / "shard-00000.safetensors"));

  // A second warm-up from the student (--init) on other trajectories: at learning rate 0 it keeps
  // the student's weights (up to the EMA's rounding of an unchanged weight), not the teacher's, and
  // records where it started.
  const auto second = tmp / "second";
  r = test::run_dojo("--threads 1 distill --data " + data +
                     " --split all --max-clips 4 --teacher-steps 4 --steps 1 --batch 2 --lr 0 "
                     "--counterfactual-copies 1 --init " +
                     (out / "checkpoint").string() + " --out " + second.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto first_student = SafetensorsFile::open(out / "checkpoint" / "model.safetensors");
  const auto second_student = SafetensorsFile::open(second / "checkpoint" / "model.safetensors");
  const auto teacher = SafetensorsFile::open(std::filesystem::path(DOJO_SOURCE_DIR) / "models" / "reference" /
                                             "wm_posttrain" / "model.safetensors");
  double from_first = 0, first_from_teacher = 0;
  for (const auto& name : first_student.keys()) {
    const auto first = first_student.tensor(name).to(torch::kFloat);
    from_first = std::max(from_first,
                          (second_student.tensor(name).to(torch::kFloat) - first).abs().max().item<double>());
    first_from_teacher = std::max(
        first_from_teacher, (teacher.tensor(name).to(torch::kFloat) - first).abs().max().item<double>());
  }
  EXPECT_LT(from_first, 1e-6);
  EXPECT_GT(first_from_teacher, 1e-4) << "the first warm-up moved the student off the teacher";
  EXPECT_EQ(
      nlohmann::json::parse(test::read_file(second / "checkpoint" / "trainer_state.json"))["extra"]["init"],
      (out / "checkpoint").string());
  r = test::run_dojo("--threads 1 distill --data " + data + " --split all --max-clips 4 --steps 1 --init " +
                     (tmp / "robot").string() + " --out " + (tmp / "bad_init").string());
  EXPECT_NE(r.exit_code, 0) << r.output;

  // Self-Forcing from the warmed-up student on a weighted mixture (the second set weighs 1), then
  // resumed for one more iteration.
  g.seed = 1;
  test::write_synthetic_dataset(tmp / "robot2", g);
  const auto sf = tmp / "self_forcing";
  const auto sf_args = "--threads 1 distill --stage self-forcing --init " + (out / "checkpoint").string() +
                       " --data " + data + ":3 --data " + (tmp / "robot2").string() +
                       " --split all --max-clips 2 --min-frames 4 --max-frames 5 --batch 1 --out " +
                       sf.string();
  r = test::run_dojo(sf_args + " --steps 3");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(sf / "critic" / "config.json"));
  r = test::run_dojo(sf_args + " --steps 4");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto summary = nlohmann::json::parse(test::read_file(sf / "distill_summary.json"));
  EXPECT_EQ(summary.at("iterations"), 4);
  EXPECT_EQ(summary.at("generator_updates"), 1) << "iteration 0 updates the student, 1-3 the critic";
  EXPECT_EQ(summary.at("critic_updates"), 3);
  const auto mixture = summary.at("mixture");
  ASSERT_EQ(mixture.size(), 2u) << summary.dump();
  EXPECT_EQ(mixture[0].at("weight"), 3.0);
  EXPECT_DOUBLE_EQ(mixture[1].at("share").get<double>(), 0.25);
  EXPECT_EQ(
      nlohmann::json::parse(test::read_file(sf / "checkpoint" / "trainer_state.json"))["extra"]["mixture"],
      mixture);
  // LoRA Self-Forcing: adapters alone train; the warmed-up student's weights stay, bit for bit.
  // Iteration 0's generator update is zero by construction (the critic starts as the teacher), so
  // the run goes on to a second generator update after one critic step.
  r = test::run_dojo("--threads 1 distill --stage self-forcing --init " + (out / "checkpoint").string() +
                     " --data " + data +
                     " --split all --max-clips 2 --min-frames 4 --max-frames 5 --batch 1 --lora 4 "
                     "--critic-steps 1 --steps 3 --out " +
                     (tmp / "sf_lora").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("distill --lora: "), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("trainable parameters (adapters), "), std::string::npos) << r.output;
  const auto warm = SafetensorsFile::open(out / "checkpoint" / "model.safetensors");
  const auto adapted = SafetensorsFile::open(tmp / "sf_lora" / "checkpoint" / "model.safetensors");
  for (const auto& name : warm.keys())
    EXPECT_TRUE(torch::equal(warm.tensor(name), adapted.tensor(name))) << name;
  const auto adapter = SafetensorsFile::open(tmp / "sf_lora" / "checkpoint" / "adapter_model.safetensors");
  EXPECT_GT(adapter.tensor("net.blocks.0.self_attn.q_proj.lora_B.default.weight").abs().max().item<float>(),
            0.f)
      << "the second generator update trained the adapters";

  r = test::run_dojo("--threads 1 distill --stage self-forcing --data " + data + " --out " +
                     (tmp / "x").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("--init"), std::string::npos) << r.output;

  // Raw robot commands (6 joints, after a baseline) and rows in the 384-d layout, from a file.
  const auto actions = tmp / "actions.jsonl";
  write_lines(actions,
              {R"({"baseline": [1, 0.5, 1.8, 0.8, 0, 0.5]})", rows(4, 6, 0.1), "", rows(4, 384, 0.0)});
  const auto tok = (std::filesystem::path(DOJO_SOURCE_DIR) / "models" / "reference" / "tokenizer").string();
  r = test::run_dojo("--threads 1 wm stream -c " + (out / "checkpoint").string() + " --tokenizer " + tok +
                     " --data " + data + " --split all --actions " + actions.string() +
                     " --frames 40 --out " + (tmp / "s.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("streamed 8 frames"), std::string::npos)
      << "the file's two chunks, then its end: " << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "s.mp4"));

  // A fast decoder distilled from the tokenizer (two steps: the plumbing), then streamed with.
  r = test::run_dojo("--threads 1 tokenizer fast-decoder --tokenizer " + tok + " --data " + data +
                     " --split all --max-clips 4 --steps 2 --batch 2 --out " + (tmp / "fd").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo("--threads 1 wm stream -c " + (out / "checkpoint").string() + " --tokenizer " + tok +
                     " --data " + data + " --split all --frames 8 --fast-decoder " +
                     (tmp / "fd" / "checkpoint").string() + " --out " + (tmp / "fast.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(tmp / "fast.mp4"));

  // The released teleop alignment at the released window takes 12 actions per step: 3 latents
  // first, then 1 per step.
  r = test::run_dojo(
      "--threads 1 wm stream -c " + (out / "checkpoint").string() + " --tokenizer " + tok + " --data " +
      data + " --split all --frames 16 --no-decode --json --window 3 --action-alignment released_teleop");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("\"frames\": 16"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("released_teleop"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("\"sink_frames\": 0"), std::string::npos) << "released modes stream without a sink";
  r = test::run_dojo("--threads 1 wm stream -c " + (out / "checkpoint").string() + " --tokenizer " + tok +
                     " --data " + data +
                     " --split all --frames 16 --no-decode --window 3 --action-alignment released_teleop "
                     "--sink-frames 1");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("attention sink needs the training action alignment"), std::string::npos)
      << r.output;
  // The plain reference recomputes an absolute sink; one at the window's edge needs the cache.
  const auto no_cache = "--threads 1 wm stream -c " + (out / "checkpoint").string() + " --tokenizer " + tok +
                        " --data " + data + " --split all --frames 8 --no-decode --no-cache";
  r = test::run_dojo(no_cache);
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("needs the KV cache on"), std::string::npos) << r.output;
  r = test::run_dojo(no_cache + " --sink-position absolute");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo("--threads 1 distill --data " + data + " --window 2 --sink-frames 3 --out " +
                     (tmp / "bad").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("must fit in the window"), std::string::npos) << r.output;

  write_lines(actions, {rows(4, 384, 0.0), "[[1, 2], [3]]"});
  r = test::run_dojo("--threads 1 wm stream -c " + (out / "checkpoint").string() + " --tokenizer " + tok +
                     " --data " + data + " --split all --actions " + actions.string() + " --no-decode");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("actions.jsonl line 2"), std::string::npos) << r.output;

  r = test::run_dojo("--threads 1 eval --student -c " + (out / "checkpoint").string() + " --tokenizer " +
                     tok + " --data " + data +
                     " --split all -n 1 --chunks 1 --json --sink-position absolute");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(r.output.find("\"student\""), std::string::npos);
  EXPECT_NE(r.output.find("\"sink_position\": \"absolute\""), std::string::npos) << r.output;
  r = test::run_dojo("--threads 1 eval -c " + (out / "checkpoint").string() + " --tokenizer " + tok +
                     " --data " + data + " --split all -n 1 --chunks 1 --sink-frames 1");
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("add --student"), std::string::npos) << r.output;
}

// `dojo wm speed` on random tiny networks: one row per decoder with frames/s that add up, the
// cache bounded by the window, and one-line errors for what it cannot time.
TEST(StreamCli, SpeedTimesEachDecoderOnRandomWeights) {
  auto r = test::run_dojo(
      "--threads 1 wm speed --arch tiny --vae-dim 8 --size 32x32 --steps 3 --window 2 --sink-frames 1 "
      "--json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto report = nlohmann::json::parse(r.output.substr(r.output.find("{\n")));
  EXPECT_EQ(report.at("window_frames"), 2);
  EXPECT_EQ(report.at("sink_frames"), 1);
  ASSERT_EQ(report.at("rows").size(), 3u);
  double kv_mib = -1;
  for (const auto& row : report.at("rows")) {
    EXPECT_EQ(row.at("frames"), 12) << row;  // 3 timed steps of 4 frames
    const double fps = row.at("steady_frames_per_second");
    EXPECT_GT(fps, 0) << row;
    EXPECT_LE(row.at("step_ms_p50").get<double>(), row.at("step_ms_max").get<double>());
    if (kv_mib >= 0) {
      EXPECT_DOUBLE_EQ(row.at("kv_cache_mib").get<double>(), kv_mib);  // the same ring
    }
    kv_mib = row.at("kv_cache_mib");
  }
  EXPECT_EQ(report["rows"][0].at("decoder"), "none");
  EXPECT_EQ(report["rows"][0].at("decode_ms_mean").get<double>() < 0.5, true);
  EXPECT_GT(report["rows"][2].at("decode_ms_mean").get<double>(), 0);  // the Wan decoder ran

  for (const auto& [args, message] : std::vector<std::pair<std::string, std::string>>{
           {"--arch huge", "--arch: unknown architecture 'huge'"},
           {"--arch tiny --decoders vq", "--decoders: unknown decoder 'vq'"},
           {"--checkpoint models/reference/wm_posttrain", "--checkpoint needs --tokenizer"},
           {"--arch tiny --steps 1", "--steps must be at least 3"}}) {
    r = test::run_dojo("wm speed --vae-dim 8 --size 32x32 " + args);
    EXPECT_NE(r.exit_code, 0) << args;
    EXPECT_NE(r.output.find(message), std::string::npos) << args << ": " << r.output;
  }
}

}  // namespace
}  // namespace dojo
