// `dojo study create | report`: the human preference study (serve/study.h); `dojo serve --study
// DIR` runs it in the browser.
#include <CLI/CLI.hpp>

#include <iostream>

#include "cli/commands.h"
#include "cli/options.h"
#include "core/atomic_file.h"
#include "core/error.h"
#include "core/log.h"
#include "core/runtime.h"
#include "serve/study_create.h"

namespace fs = std::filesystem;

namespace dojo::cli {
namespace {

struct CreateArgs {
  std::string dir, demo = "dojo_demo", tokenizer, data, fast_decoder, videos, name, split = "val";
  std::vector<std::string> teachers, students, models;
  int episodes = 6, chunks = 2;
  uint64_t seed = 0;
  std::string device = "cpu", precision = "fp32";
};

serve::StudyModel parse_model(const std::string& text, bool student, const std::string& flag) {
  const auto eq = text.find('=');
  if (eq == std::string::npos || eq == 0 || eq + 1 == text.size())
    throw UsageError(flag + " '" + text + "': expected NAME=CHECKPOINT");
  serve::StudyModel m;
  m.name = text.substr(0, eq);
  m.checkpoint = text.substr(eq + 1);
  m.student = student;
  return m;
}

int run_create(const CreateArgs& a) {
  if (!a.videos.empty()) {
    if (a.models.size() < 2) throw UsageError("study create --videos: name the clips with --models A,B");
    const auto study = serve::create_study_from_videos(a.dir, a.videos, a.models, a.name);
    LOG_INFO("study: ", study.items.size(), " items, ", study.trials().size(), " trials in ", a.dir);
    return 0;
  }
  serve::StudyFromModels o;
  o.dir = a.dir;
  o.name = a.name;
  for (const auto& t : a.teachers) o.models.push_back(parse_model(t, false, "--model"));
  for (const auto& s : a.students) o.models.push_back(parse_model(s, true, "--student"));
  const fs::path demo = a.demo;
  if (o.models.empty()) {  // the demo's student against its teacher
    DOJO_CHECK(
        fs::exists(demo / "student" / "checkpoint") && fs::exists(demo / "wm_posttrain" / "checkpoint"),
        "study create: no models (give --model / --student NAME=CHECKPOINT, or --demo DIR of a finished "
        "`dojo demo`)");
    o.models.push_back({"student", demo / "student" / "checkpoint", true,
                        fs::exists(demo / "fast_decoder" / "checkpoint")
                            ? demo / "fast_decoder" / "checkpoint"
                            : fs::path()});
    o.models.push_back({"teacher", demo / "wm_posttrain" / "checkpoint", false, {}});
  }
  if (!a.fast_decoder.empty())
    for (auto& m : o.models)
      if (m.student) m.fast_decoder = a.fast_decoder;
  o.tokenizer = !a.tokenizer.empty() ? fs::path(a.tokenizer) : demo / "tokenizer" / "checkpoint";
  o.data = !a.data.empty() ? fs::path(a.data) : demo / "robot";
  o.split = a.split;
  o.episodes = a.episodes;
  o.chunks = a.chunks;
  o.seed = a.seed;
  o.device = parse_device(a.device);
  o.precision = parse_precision(a.precision);
  ScopedThreads matmul_bound(matmul_bound_command_threads("study create", o.device.is_cuda()));
  const auto study = serve::create_study_from_models(o);
  LOG_INFO("study: ", study.items.size(), " items, ", study.trials().size(), " trials in ", a.dir,
           "; run it with: dojo serve --study ", a.dir);
  return 0;
}

int run_report(const std::string& dir, std::string json, std::string md, std::string html) {
  const auto study = serve::Study::open(dir);
  serve::VoteStore votes(fs::path(dir) / "votes.sqlite");
  const auto report = serve::make_report(study, votes.all());
  if (json.empty()) json = (fs::path(dir) / "report.json").string();
  if (md.empty()) md = (fs::path(dir) / "report.md").string();
  if (html.empty()) html = (fs::path(dir) / "report.html").string();
  write_file_atomic(json, report.to_json().dump(2) + "\n");
  write_file_atomic(md, report.to_markdown());
  write_file_atomic(html, report.to_html());
  std::cout << report.to_markdown();
  LOG_INFO("study: report written to ", json, ", ", md, ", ", html);
  return 0;
}

}  // namespace

void register_study(CLI::App& app) {
  auto* study = app.add_subcommand("study", "The human preference study: create one, report its votes");
  study->require_subcommand(1);

  auto c = std::make_shared<CreateArgs>();
  auto* create = study->add_subcommand("create", "Render two or more models' rollouts into a study");
  create->add_option("dir", c->dir, "Study directory to create")->required();
  create->add_option("--model", c->teachers, "NAME=CHECKPOINT of a teacher-style model (12-frame chunks)");
  create->add_option("--student", c->students, "NAME=CHECKPOINT of a streaming student");
  create->add_option("--demo", c->demo, "Without --model/--student: the demo's student vs teacher")
      ->capture_default_str();
  create->add_option("--tokenizer", c->tokenizer, "Tokenizer checkpoint (default: the demo's)");
  create->add_option("--fast-decoder", c->fast_decoder, "Fast decoder for the students");
  create->add_option("--data", c->data,
                     "Dataset whose episodes are rolled out (default: the demo's robot data)");
  add_split_option(create, c->split);
  create->add_option("--episodes", c->episodes, "Episodes (items) in the study")
      ->check(CLI::Range(1, 10000))
      ->capture_default_str();
  create->add_option("--chunks", c->chunks, "12-frame chunks per clip")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  create->add_option("--seed", c->seed, "Sampling seed")->capture_default_str();
  create->add_option("--videos", c->videos,
                     "Take given clips instead: SOURCE/ID/truth.mp4 and SOURCE/ID/MODEL.mp4");
  create->add_option("--models", c->models, "With --videos: the model names (clip file stems)")
      ->delimiter(',');
  create->add_option("--name", c->name, "Study name shown in the report");
  add_device_option(create, c->device);
  add_precision_option(create, c->precision);
  create->callback([c] { set_action([c] { return run_create(*c); }); });

  auto r = std::make_shared<std::array<std::string, 4>>();
  auto* report = study->add_subcommand("report", "Win rates with 95% intervals: JSON, markdown and HTML");
  report->add_option("dir", (*r)[0], "Study directory")->required();
  report->add_option("--json", (*r)[1], "JSON output (default DIR/report.json)");
  report->add_option("--md", (*r)[2], "Markdown output (default DIR/report.md)");
  report->add_option("--html", (*r)[3], "HTML output (default DIR/report.html)");
  report->callback([r] { set_action([r] { return run_report((*r)[0], (*r)[1], (*r)[2], (*r)[3]); }); });
}

}  // namespace dojo::cli
