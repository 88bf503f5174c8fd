// `dojo serve`: the HTTP + WebSocket server (serve/server.h) over the reference set, the demo's
// models or given ones.
#include <CLI/CLI.hpp>

#include <csignal>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <optional>
#include <thread>

#include "cli/commands.h"
#include "cli/model_args.h"
#include "cli/options.h"
#include "core/error.h"
#include "core/log.h"
#include "core/runtime.h"
#include "serve/load.h"
#include "serve/model_host.h"
#include "serve/server.h"

namespace fs = std::filesystem;

namespace dojo::cli {
namespace {

struct ServeArgs {
  serve::ServeOptions server;
  std::string demo, student, teacher, tokenizer, fast_decoder, data, split = "val";  // demo "": dojo_demo
  std::string text_context;  // every model's prompt embedding (empty: zeros)
  data::OpenOptions open;    // --embodiment, --camera for LeRobot data
  std::string device = "cpu", precision = "fp32";
  bool no_teacher = false, no_cuda_graphs = false;
  int teacher_steps = 0;
};

fs::path pick_existing(const std::string& given, const fs::path& fallback) {
  return !given.empty() ? fs::path(given) : (fs::exists(fallback) ? fallback : fs::path());
}

void set_runtime(const ServeArgs& a, serve::ModelHost::Options& o) {
  for (auto& model : o.models) model.text_context = a.text_context;
  o.split = a.split;
  o.open = a.open;
  o.device = parse_device(a.device);
  o.precision = parse_precision(a.precision);
  o.cuda_graphs = !a.no_cuda_graphs;
}

// Without --demo, --student, --teacher or --study: the reference set where it has a student (its
// student with its fast decoder when it has one, and its post-trained world model as the teacher),
// sessions starting from held-out DojoSim episodes made here unless --data is given.
std::optional<serve::ModelHost::Options> reference_host_options(const ServeArgs& a) {
  if (!a.demo.empty() || !a.student.empty() || !a.teacher.empty() || !a.server.study.empty())
    return std::nullopt;
  const auto student = reference_student();
  if (student.empty()) return std::nullopt;
  const auto reference = default_reference_dir();
  serve::ModelHost::Options o;
  serve::ModelSpec s;
  s.name = "student";
  s.checkpoint = student;
  s.tokenizer = pick_existing(a.tokenizer, reference / "tokenizer");
  DOJO_CHECK(!s.tokenizer.empty(), "serve: the reference set in " + reference.string() + " has no tokenizer");
  s.fast_decoder = reference_model_fast_decoder(a.fast_decoder, !a.tokenizer.empty());
  o.models.push_back(s);
  const auto teacher = reference / "wm_posttrain";
  if (!a.no_teacher && fs::exists(teacher / "config.json")) {
    serve::ModelSpec t;
    t.name = "teacher";
    t.streaming = false;
    t.checkpoint = teacher;
    t.tokenizer = s.tokenizer;
    t.teacher_steps = a.teacher_steps;
    o.models.push_back(t);
  }
  LOG_INFO("serve: the reference set in ", reference.string(), ": student",
           s.fast_decoder.empty() ? "" : " (fast decoder)", o.models.size() > 1 ? " and teacher" : "");
#ifdef DOJO_WITH_SIM
  o.data = a.data.empty() ? fs::path(default_eval_data()) : fs::path(a.data);
#else
  o.data = a.data;  // without DojoSim and --data, clients upload their start images
#endif
  set_runtime(a, o);
  return o;
}

// The models: given ones, else the reference set's (above), else those `dojo demo` wrote into
// --demo.
serve::ModelHost::Options host_options(const ServeArgs& a) {
  if (auto reference = reference_host_options(a)) return *reference;
  serve::ModelHost::Options o;
  const fs::path demo = a.demo.empty() ? "dojo_demo" : a.demo;
  const auto tokenizer = pick_existing(a.tokenizer, demo / "tokenizer" / "checkpoint");
  const auto student = pick_existing(a.student, demo / "student" / "checkpoint");
  const auto teacher =
      a.no_teacher ? fs::path() : pick_existing(a.teacher, demo / "wm_posttrain" / "checkpoint");
  if (!a.server.study.empty() && a.tokenizer.empty() && a.student.empty() && a.teacher.empty() &&
      (tokenizer.empty() || (student.empty() && teacher.empty())))
    return o;  // a study needs no model: its clips are rendered
  DOJO_CHECK(!tokenizer.empty(),
             "serve: no tokenizer (give --tokenizer, or --demo DIR of a finished `dojo demo`)");
  DOJO_CHECK(!student.empty() || !teacher.empty(),
             "serve: no model (give --student or --teacher, or --demo DIR of a finished `dojo demo`)");
  if (!student.empty()) {
    serve::ModelSpec s;
    s.name = "student";
    s.checkpoint = student;
    s.tokenizer = tokenizer;
    s.fast_decoder =
        pick_existing(a.fast_decoder, a.student.empty() ? demo / "fast_decoder" / "checkpoint" : fs::path());
    o.models.push_back(s);
  }
  if (!teacher.empty()) {
    serve::ModelSpec t;
    t.name = "teacher";
    t.streaming = false;
    t.checkpoint = teacher;
    t.tokenizer = tokenizer;
    t.teacher_steps = a.teacher_steps;
    o.models.push_back(t);
  }
  o.data = pick_existing(a.data, demo / "robot");
  set_runtime(a, o);
  return o;
}

int run_serve(const ServeArgs& a) {
  auto host = std::make_shared<serve::ModelHost>(host_options(a));
  ScopedThreads matmul_bound(matmul_bound_command_threads("serve", parse_device(a.device).is_cuda()));
  // SIGINT / SIGTERM are taken by sigwait below, on this thread only: block them before any
  // thread starts so that every thread inherits the mask.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  serve::Server server(a.server, host);
  const auto port = server.start();  // /health answers 503 while the models load
  LOG_INFO("serve: listening on ", a.server.tls_cert.empty() ? "http" : "https", "://", a.server.host, ":",
           port, "/",
           a.server.token.empty() ? "" : "#token=... (the token in the fragment, never sent in a URL)");
  std::thread loader([&] {
    try {
      host->load();
      LOG_INFO("serve: ready");
    } catch (const std::exception& e) {
      LOG_ERROR("serve: ", e.what());
      kill(getpid(), SIGTERM);  // a server without models serves nothing: stop with the error above
    }
  });
  int signal = 0;
  sigwait(&signals, &signal);
  LOG_INFO("serve: stopping (signal ", signal, "): finishing sessions and recordings");
  loader.join();
  server.stop();
  return host->ready() ? 0 : 1;
}

}  // namespace

void register_serve_load(CLI::App& app) {
  auto o = std::make_shared<serve::LoadOptions>();
  auto json = std::make_shared<bool>(false);
  auto* cmd = app.add_subcommand("serve-load",
                                 "Load-test a running `dojo serve`: N concurrent sessions for a "
                                 "bounded time; frames/s, latency percentiles, errors, server memory");
  cmd->add_option("--host", o->host, "Server address")->capture_default_str();
  cmd->add_option("--port", o->port, "Server port")->capture_default_str();
  cmd->add_option("--token", o->token, "Access token");
  cmd->add_option("--sessions,-n", o->sessions, "Concurrent sessions")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  cmd->add_option("--seconds", o->seconds, "How long each session runs")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--mode", o->mode,
                  "step (policy round trips), live (teleoperation) or study (preference-study voters)")
      ->check(CLI::IsMember({"step", "live", "study"}))
      ->capture_default_str();
  cmd->add_option("--model", o->model, "Model name (default: the server's first)");
  add_json_option(cmd, *json);
  cmd->callback([o, json] {
    set_action([o, json] {
      const auto r = serve::run_load(*o);
      if (*json) {
        std::printf("%s\n", r.to_json().dump().c_str());
      } else if (o->mode == "study") {
        std::printf(
            "%d voter(s), %.0f s: %lld votes acknowledged (%.1f/s); vote latency p50 %.1f ms, p95 %.1f ms, "
            "p99 %.1f ms; %lld answers 503 (retried); failed voters %lld; server RSS %.1f -> %.1f MiB\n",
            o->sessions, o->seconds, static_cast<long long>(r.votes_acknowledged),
            r.votes_acknowledged / o->seconds, r.latency_ms_p50, r.latency_ms_p95, r.latency_ms_p99,
            static_cast<long long>(r.refusals), static_cast<long long>(r.failed_sessions),
            r.server_rss_mib_before, r.server_rss_mib_after);
        for (const auto& f : r.failures) std::printf("  failed: %s\n", f.c_str());
      } else {
        std::printf("%d %s session(s), %.0f s: frames/s per session", o->sessions, o->mode.c_str(),
                    o->seconds);
        for (double f : r.frames_per_second) std::printf(" %.1f", f);
        std::printf(
            "; latency p50 %.1f ms, p95 %.1f ms, p99 %.1f ms; errors %lld, failed sessions %lld, refused at "
            "the cap %lld, dropped frames %lld; server RSS %.1f -> %.1f MiB\n",
            r.latency_ms_p50, r.latency_ms_p95, r.latency_ms_p99, static_cast<long long>(r.errors),
            static_cast<long long>(r.failed_sessions), static_cast<long long>(r.refused_sessions),
            static_cast<long long>(r.frames_dropped), r.server_rss_mib_before, r.server_rss_mib_after);
        for (const auto& f : r.failures) std::printf("  failed: %s\n", f.c_str());
      }
      // Sessions declined at the cap are the server's clear answer, not a failure of the run.
      return r.failed_sessions == 0 && r.errors == 0 && r.server_alive_after ? 0 : 1;
    });
  });
}

void register_serve(CLI::App& app) {
  auto a = std::make_shared<ServeArgs>();
  auto* cmd =
      app.add_subcommand("serve", "Serve live teleoperation, the rollout API and the preference study");
  cmd->add_option("--demo", a->demo,
                  "Take the models and start frames from this `dojo demo` output (default: the reference "
                  "set on held-out DojoSim episodes when the set has a student, else dojo_demo)");
  cmd->add_option("--student", a->student, "Student checkpoint (streams 4 frames per step)");
  cmd->add_option("--teacher", a->teacher, "Teacher checkpoint (12 frames per chunk, slower)");
  cmd->add_flag("--no-teacher", a->no_teacher, "Host the student only");
  cmd->add_option("--teacher-steps", a->teacher_steps,
                  "The teacher's sampler steps a chunk (default: the trained sampler's, 35; fewer: faster)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--tokenizer", a->tokenizer, "Tokenizer checkpoint");
  cmd->add_option("--fast-decoder", a->fast_decoder, "Fast streaming decoder for the student");
  cmd->add_option("--text-context", a->text_context,
                  "The prompt embedding every model cross-attends to: a .pt file holding the tensor or a "
                  "safetensors file with one tensor 'context', [L, C] (default: zeros; docs/checkpoints.md)");
  cmd->add_option("--data", a->data,
                  "Dataset whose episodes sessions start from (default: with the reference set, 8 held-out "
                  "DojoSim episodes made on the spot; else the demo's robot data)");
  add_split_option(cmd, a->split);
  cmd->add_option(
         "--embodiment", a->open.embodiment,
         "LeRobot data: the robot whose raw commands sessions send (gr1, g1, yam, agibot); auto reads "
         "info.json's robot_type, never the path")
      ->capture_default_str();
  cmd->add_option("--camera", a->open.camera, "LeRobot data: video key (default: the robot's camera)");
  cmd->add_option("--host", a->server.host, "Address to bind (0.0.0.0 exposes the server)")
      ->capture_default_str();
  cmd->add_option("--port", a->server.port, "Port (0: any free one)")->capture_default_str();
  cmd->add_option("--token", a->server.token,
                  "Require this token (an Authorization: Bearer header, or open the page as /#token=TOKEN)");
  cmd->add_flag("--insecure", a->server.insecure, "Allow a --host other than loopback without --token");
  cmd->add_option("--max-sessions", a->server.max_sessions, "Concurrent sessions and rollout jobs")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  cmd->add_option("--max-rollout-frames", a->server.max_rollout_frames,
                  "Frames one POST /v1/rollout may ask for")
      ->check(CLI::Range(int64_t{2}, int64_t{1} << 20))
      ->capture_default_str();
  cmd->add_option("--max-rollout-seconds", a->server.max_rollout_seconds,
                  "Seconds a rollout may generate before it stops with 503")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cmd->add_option("--study-threads", a->server.study_threads, "Threads answering the study's requests")
      ->check(CLI::Range(1, 64))
      ->capture_default_str();
  cmd->add_option("--fps", a->server.fps, "Live frame rate (0: 10 frames/s, the released rate)")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option(
      "--tls-cert", a->server.tls_cert,
      "PEM certificate chain: serve HTTPS (browsers give Gamepad and WebXR only to secure pages)");
  cmd->add_option("--tls-key", a->server.tls_key, "PEM private key of --tls-cert");
  cmd->add_option("--study", a->server.study, "Serve this preference study at /study (dojo study create)");
  cmd->add_option("--recordings", a->server.recordings, "Where session recordings go")->capture_default_str();
  cmd->add_option("--jpeg-quality", a->server.jpeg_quality, "JPEG quality of streamed frames")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  add_device_option(cmd, a->device);
  add_precision_option(cmd, a->precision);
  cmd->add_flag(
      "--no-cuda-graphs", a->no_cuda_graphs,
      "On CUDA, the streaming models dispatch their hops op by op instead of replaying CUDA graphs");
  cmd->callback([a] { set_action([a] { return run_serve(*a); }); });
}

}  // namespace dojo::cli
