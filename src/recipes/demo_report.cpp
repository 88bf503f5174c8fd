#include "recipes/demo_report.h"

#include <cmath>
#include <cstdio>
#include <vector>

#include "core/atomic_file.h"
#include "eval/html_report.h"

namespace fs = std::filesystem;

namespace dojo::recipes {
namespace {

std::string fixed(const nlohmann::json& v, int digits = 2) {
  if (!v.is_number()) return "-";
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.*f", digits, v.get<double>());
  return buf;
}

const nlohmann::json& source(const nlohmann::json& split, const char* name) {
  static const nlohmann::json kNone = nlohmann::json::object();
  return split.contains(name) ? split.at(name) : kNone;
}

nlohmann::json value(const nlohmann::json& source, const char* key) {
  return source.contains(key) ? source.at(key) : nlohmann::json(nullptr);
}

// Markdown and HTML rows of one evaluation (one row per split).
struct Tables {
  std::vector<std::string> header;
  std::vector<std::vector<std::string>> rows;
};

Tables score_table(const nlohmann::json& evals, const std::string& label) {
  Tables t;
  t.header = {"models",
              "split",
              "PSNR",
              "copy-frame PSNR",
              "tokenizer PSNR",
              "SSIM",
              "keypoint error (px)",
              "copy-frame keypoint error",
              "detection",
              "ground-truth detection",
              "released protocol PSNR (frame 0 incl.): model / copy-frame"};
  for (const auto& s : evals) {
    const auto &wm = source(s, "world_model"), &copy = source(s, "copy_frame"), &tok = source(s, "tokenizer"),
               &gt = source(s, "ground_truth");
    t.rows.push_back({label, s.value("split", ""), fixed(value(wm, "psnr")), fixed(value(copy, "psnr")),
                      fixed(value(tok, "psnr")), fixed(value(wm, "ssim"), 3),
                      fixed(value(wm, "keypoint_error_px")), fixed(value(copy, "keypoint_error_px")),
                      fixed(value(wm, "detection"), 3), fixed(value(gt, "detection"), 3),
                      fixed(value(wm, "psnr_all_frames")) + " / " + fixed(value(copy, "psnr_all_frames"))});
  }
  return t;
}

Tables sensitivity_table(const nlohmann::json& evals, const std::string& label) {
  Tables t;
  t.header = {"models",   "split", "PSNR, true actions", "shuffled", "zero", "keypoint error, true actions",
              "shuffled", "zero"};
  for (const auto& s : evals) {
    const auto &wm = source(s, "world_model"), &sh = source(s, "shuffled_actions"),
               &z = source(s, "zero_actions");
    t.rows.push_back({label, s.value("split", ""), fixed(value(wm, "psnr")), fixed(value(sh, "psnr")),
                      fixed(value(z, "psnr")), fixed(value(wm, "keypoint_error_px")),
                      fixed(value(sh, "keypoint_error_px")), fixed(value(z, "keypoint_error_px"))});
  }
  return t;
}

void append(Tables& to, const Tables& more) {
  to.rows.insert(to.rows.end(), more.rows.begin(), more.rows.end());
}

std::string markdown(const Tables& t) {
  std::string s = "|";
  for (const auto& h : t.header) s += " " + h + " |";
  s += "\n|";
  for (size_t i = 0; i < t.header.size(); ++i) s += "---|";
  s += "\n";
  for (const auto& r : t.rows) {
    s += "|";
    for (const auto& c : r) s += " " + c + " |";
    s += "\n";
  }
  return s;
}

// A per-frame curve of one source, as a chart series (frames with no value are skipped).
eval::Series curve(const nlohmann::json& split, const char* source_name, const char* metric,
                   const std::string& name) {
  eval::Series s;
  s.name = name;
  if (!split.contains("per_frame") || !split["per_frame"].contains(source_name)) return s;
  const auto& values = split["per_frame"][source_name].value(metric, nlohmann::json::array());
  for (size_t t = 0; t < values.size(); ++t)
    if (values[t].is_number()) s.x.push_back(static_cast<double>(t)), s.y.push_back(values[t].get<double>());
  return s;
}

}  // namespace

std::string write_demo_report(const fs::path& out, const nlohmann::json& stages) {
  const auto& evals = stages["eval"]["result"];
  const bool reference = stages.contains("eval_reference");
  Tables scores = score_table(evals, "demo"), sensitivity = sensitivity_table(evals, "demo");
  if (reference) {
    append(scores, score_table(stages["eval_reference"]["result"], "reference"));
    append(sensitivity, sensitivity_table(stages["eval_reference"]["result"], "reference"));
  }
  const bool student = stages.contains("eval_student");
  if (student) {
    append(scores, score_table(stages["eval_student"]["result"]["splits"], "student"));
    append(sensitivity, sensitivity_table(stages["eval_student"]["result"]["splits"], "student"));
  }
  std::string md = markdown(scores) + "\nAction sensitivity:\n\n" + markdown(sensitivity);
  Tables speed;
  if (student) {
    speed.header = {"split", "teacher frames/s", "student frames/s"};
    const auto& st = stages["eval_student"]["result"]["splits"];
    for (size_t i = 0; i < evals.size() && i < st.size(); ++i)
      speed.rows.push_back({evals[i].value("split", ""), fixed(value(evals[i], "frames_per_second"), 1),
                            fixed(value(st[i], "frames_per_second"), 1)});
    const auto& stream = stages["eval_student"]["result"]["streaming"];
    md +=
        "\nGenerated frames/s (rollouts of the evaluation, same batches):\n\n" + markdown(speed) +
        "\nStreaming 600 frames at batch 1 (fast decoder): " + fixed(value(stream, "frames_per_second"), 1) +
        " frames/s, step p50 " + fixed(value(stream, "step_ms_p50"), 1) + " ms, p95 " +
        fixed(value(stream, "step_ms_p95"), 1) + " ms, RSS " + fixed(value(stream, "rss_mib_frame_100"), 0) +
        " MiB at frame 100, " + fixed(value(stream, "rss_mib_frame_600"), 0) + " MiB at frame 600.\n";
  }
  write_file_atomic(out / "eval.md", md);

  // The rollouts' length as the evaluation recorded it (every split rolls out the same chunks).
  const int64_t frames = evals.empty() ? 0 : evals[0].value("frames_per_video", int64_t{0});
  eval::HtmlReport html("DreamDojo.cpp demo on DojoSim");
  const bool tokenizer_copied =
      stages.contains("tokenizer") &&
      stages["tokenizer"].value("result", nlohmann::json::object()).contains("copied_from");
  html.paragraph(
      "Everything below was made by `dojo demo` on this machine: DojoSim generated human and robot episodes; "
      "a "
      "small latent action model learned actions from video alone; " +
      std::string(tokenizer_copied
                      ? "a small Wan2.1-architecture tokenizer trained beforehand gave the latent "
                        "space (copied in, as the paper takes its VAE pretrained); "
                      : "a small Wan2.1-architecture tokenizer learned the latent space; ") +
      "a keypoint probe learned to find the arm and the hand; the action-conditioned DiT "
      "was "
      "pretrained on human video with latent actions and post-trained on robot actions. It then rolled out " +
      std::to_string(frames) +
      "-frame videos (chunks of 12 actions, each started from the last frame of the one "
      "before) from the first frame and the actions of episodes it never saw.");
  html.heading("Rollouts vs ground truth");
  html.paragraph(
      "PSNR/SSIM per frame (piq conventions) on the predicted frames 1-" + std::to_string(frames - 1) +
      " (frame 0, which every method is "
      "given, is left out: copy-frame's frame 0 is the ground truth itself), mean per video, then over "
      "videos; the last column is the released protocol's PSNR with frame 0 included. The copy-frame "
      "baseline repeats "
      "the real first frame: what a model that ignores the actions gets for free. The tokenizer round trip "
      "of "
      "the ground truth is the ceiling for any rollout decoded by this tokenizer. The keypoint error is the "
      "distance between the probe's arm keypoints (gripper, wrist, elbow) on the generated frames and the "
      "simulator's; the detection rate is the share of the visible keypoints the probe places within 3 px "
      "of the truth there, next to the rate on the real frames.");
  html.table(scores.header, scores.rows);
  if (student) {
    html.heading("The real-time student");
    const bool self_forcing =
        stages.value(nlohmann::json::json_pointer("/student/result/self_forcing_iterations"), 0) > 0;
    html.paragraph(
        std::string("The post-trained world model distilled into a causal 4-step student (warm-up on "
                    "the teacher's ODE trajectories") +
        (self_forcing ? ", then Self-Forcing" : "") +
        "), streamed one latent frame (4 video frames) per step through its KV cache and decoded "
        "by the fast decoder. Its rows in the tables above are labelled \"student\". Generated "
        "frames/s of the evaluation rollouts:");
    html.table(speed.header, speed.rows);
    const auto& stream = stages["eval_student"]["result"]["streaming"];
    html.paragraph("Streaming 600 frames at batch 1: " + fixed(value(stream, "frames_per_second"), 1) +
                   " frames/s, step latency p50 " + fixed(value(stream, "step_ms_p50"), 1) + " ms, p95 " +
                   fixed(value(stream, "step_ms_p95"), 1) + " ms; resident memory " +
                   fixed(value(stream, "rss_mib_frame_100"), 0) + " MiB at frame 100 and " +
                   fixed(value(stream, "rss_mib_frame_600"), 0) +
                   " MiB at frame 600. The 600 frames, from a "
                   "held-out episode's first frame with its recorded actions repeated:");
    if (fs::exists(out / "student_600_frames.mp4"))
      html.video(out / "student_600_frames.mp4", "the student streaming 600 frames (60 s at 10 Hz)");
  }
  html.heading("Does the model use the actions?");
  html.paragraph(
      "The same rollouts driven by another episode's actions (shuffled) and by zero actions (hold still). A "
      "model that follows its actions is clearly best with the true ones.");
  html.table(sensitivity.header, sensitivity.rows);
  std::vector<std::vector<std::string>> latent_rows;
  for (const auto& s : evals) {
    std::vector<std::string> row = {s.value("split", "")};
    for (const auto& v : s.value("tokenizer_psnr_by_latent", nlohmann::json::array()))
      row.push_back(fixed(v));
    latent_rows.push_back(row);
  }
  html.paragraph(
      "Tokenizer round-trip PSNR by a frame's latent index within its chunk (0: the conditioning "
      "frame; later latents each merge four frames of motion):");
  html.table({"split", "latent 0", "latent 1", "latent 2", "latent 3"}, latent_rows);
  for (const auto& s : evals) {
    const std::string split = s.value("split", "");
    html.line_chart(split + ": keypoint error over time",
                    {curve(s, "world_model", "keypoint_error_px", "world model"),
                     curve(s, "copy_frame", "keypoint_error_px", "copy frame"),
                     curve(s, "shuffled_actions", "keypoint_error_px", "shuffled actions"),
                     curve(s, "ground_truth", "keypoint_error_px", "probe on ground truth")},
                    "frame", "pixels");
    html.line_chart(
        split + ": PSNR over time",
        {curve(s, "world_model", "psnr", "world model"), curve(s, "copy_frame", "psnr", "copy frame"),
         curve(s, "tokenizer", "psnr", "tokenizer round trip")},
        "frame", "dB");
  }
  html.paragraph(
      "Side by side, enlarged 4x: ground truth (simulator keypoints) | world model | copy frame 0 | "
      "tokenizer round trip (probe keypoints: red gripper, green wrist, blue elbow).");
  for (const auto& s : evals)
    for (const auto& v : s.value("per_video", nlohmann::json::array()))
      if (v.contains("video") && fs::exists(v["video"].get<std::string>()))
        html.video(v["video"].get<std::string>(),
                   s.value("split", "") + " / " + v.value("episode", "") + ": PSNR " +
                       fixed(value(source(v, "world_model"), "psnr")) + " vs copy frame " +
                       fixed(value(source(v, "copy_frame"), "psnr")) + ", keypoint error " +
                       fixed(value(source(v, "world_model"), "keypoint_error_px")) + " vs " +
                       fixed(value(source(v, "copy_frame"), "keypoint_error_px")) + " px");

  html.heading("Training");
  auto series = [&](const fs::path& csv, const char* column, const std::string& name) {
    return fs::exists(csv) ? eval::read_csv_series(csv, "step", column, name) : eval::Series{name, {}, {}};
  };
  html.line_chart("World model: flow-matching loss",
                  {series(out / "wm_pretrain" / "loss.csv", "loss", "pretrain (human, latent actions)"),
                   series(out / "wm_posttrain" / "loss.csv", "loss", "post-train (robot actions)")},
                  "step", "loss", true, 20);
  if (fs::exists(out / "tokenizer" / "loss.csv"))  // trained here, not copied in
    html.line_chart("Tokenizer: reconstruction MSE",
                    {series(out / "tokenizer" / "loss.csv", "recon", "recon")}, "step", "mse", true, 20);
  html.line_chart("LAM: reconstruction PSNR", {series(out / "lam" / "loss.csv", "psnr", "psnr")}, "step",
                  "dB", false, 20);
  html.line_chart("Keypoint probe: loss", {series(out / "probe" / "loss.csv", "loss", "loss")}, "step",
                  "loss", true, 20);
  html.heading("Data");
  html.video(out / "preview_human.mp4", "human episodes (no actions)");
  html.video(out / "preview_robot.mp4", "robot episodes");
  html.heading("Stages");
  std::vector<std::vector<std::string>> rows;
  for (const char* name : {"data", "lam", "tokenizer", "probe", "wm_pretrain", "wm_posttrain", "student",
                           "fast_decoder", "eval", "eval_student", "eval_reference"})
    if (stages.contains(name))
      rows.push_back(
          {name, fixed(stages[name].value("seconds", 0.0), 1) + " s",
           std::string(name).rfind("eval", 0) == 0 ? "(tables above)" : stages[name]["result"].dump()});
  html.table({"stage", "time when it ran", "result"}, rows);
  html.write(out / "report.html");
  return md;
}

}  // namespace dojo::recipes
