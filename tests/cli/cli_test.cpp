// End-to-end checks of the `dojo` executable: help, version JSON, bad usage.
#include <algorithm>
#include <cstdio>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <sstream>

#include "core/blas_kernels.h"
#include "test_util.h"

namespace dojo {

TEST(Cli, HelpListsCommands) {
  const auto result = test::run_dojo("--help");
  EXPECT_EQ(result.exit_code, 0);
  for (const char* name : {"version", "ckpt", "video", "bench"})
    EXPECT_NE(result.output.find(name), std::string::npos) << name;
}

// The matmul rooflines in both training precisions: a row each, measured (a positive rate).
TEST(Cli, BenchMeasuresTheMatmulRooflineInFloat32AndBf16) {
  const auto result =
      test::run_dojo("--threads 1 bench --only matmul_f32 matmul_bf16 -r 1 --warmup 0 --json");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto report = nlohmann::json::parse(result.output.substr(result.output.find('{')));
  std::map<std::string, double> rate;
  for (const auto& row : report.at("rows")) rate[row.at("name")] = row.at("mean");
  EXPECT_GT(rate["matmul_f32"], 0);
  EXPECT_GT(rate["matmul_bf16"], 0);
}

TEST(Cli, VersionJson) {
  const auto result = test::run_dojo("--threads 2 version --json");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto info = nlohmann::json::parse(result.output);
  EXPECT_EQ(info["threads"], 2);
  EXPECT_EQ(info["git_commit"].get<std::string>().empty(), false);
  // The commit is read at build time: after a new commit, a rebuild names it (not the one the
  // build directory was configured at).
  const auto git =
      test::run_command("git -C '" + std::string(DOJO_SOURCE_DIR) + "' rev-parse --short=12 HEAD");
  if (git.exit_code == 0) {  // a source tree without git has no commit to compare with
    const auto head = git.output.substr(0, git.output.find_last_not_of("\n") + 1);
    EXPECT_EQ(info["git_commit"].get<std::string>().rfind(head, 0), 0u) << head;
  }
  EXPECT_TRUE(info["cuda_available"].is_boolean());
}

// A copy of the sources inside another repository (vendored, exported into a monorepo) reports no
// commit rather than the other repository's.
TEST(Cli, VersionNamesOnlyThisProjectsOwnCommit) {
  test::TempDir tmp;
  const auto outer = tmp / "outer";
  auto r = test::run_command("mkdir -p '" + (outer / "dojo").string() + "' && git -C '" + outer.string() +
                             "' init -q && git -C '" + outer.string() +
                             "' -c user.name=t -c user.email=t@t commit -q --allow-empty -m other");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto script = std::string(DOJO_SOURCE_DIR) + "/cmake/git_commit.cmake";
  r = test::run_command("cmake -DSOURCE_DIR='" + (outer / "dojo").string() + "' -DOUT='" +
                        (tmp / "h").string() + "' -P '" + script + "'");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_NE(test::read_file(tmp / "h").find("DOJO_GIT_COMMIT \"unknown\""), std::string::npos)
      << test::read_file(tmp / "h");
}

// OpenBLAS on a CPU newer than itself runs its SSE3 kernels at a quarter of the speed; the
// executable then starts itself again with OPENBLAS_CORETYPE set (core/blas_kernels.h). This
// process was started that way, so the variable is taken away for the child.
TEST(Cli, OpenBlasRunsKernelsThisCpuSupports) {
  const char* set = std::getenv("OPENBLAS_CORETYPE");
  const std::string saved = set != nullptr ? set : "";
  unsetenv("OPENBLAS_CORETYPE");
  const auto result = test::run_dojo("version --json");
  if (set != nullptr) setenv("OPENBLAS_CORETYPE", saved.c_str(), 1);
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto info = nlohmann::json::parse(result.output);
  if (!info.contains("blas_kernels")) GTEST_SKIP() << "the BLAS is not OpenBLAS: " << info["blas"];
  if (blas_kernels_for_this_cpu().empty()) GTEST_SKIP() << "a CPU without AVX2";
  EXPECT_FALSE(is_fallback_blas_kernels(info["blas_kernels"].get<std::string>())) << info["blas_kernels"];
}

TEST(Cli, UnknownCommandFailsWithUsageError) {
  const auto result = test::run_dojo("frobnicate");
  EXPECT_EQ(result.exit_code, 2);
  EXPECT_NE(result.output.find("unknown command 'dojo frobnicate'"), std::string::npos) << result.output;
  EXPECT_EQ(result.output.find("terminate"), std::string::npos);
}

// A mistyped subcommand is named as such, with the nearest real one, also with --help, and
// options with values before it are skipped over.
TEST(Cli, MistypedSubcommandIsNamed) {
  auto r = test::run_dojo("wm rolout");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_NE(r.output.find("unknown command 'dojo wm rolout' (did you mean 'dojo wm rollout'?)"),
            std::string::npos)
      << r.output;
  r = test::run_dojo("nonsense --help");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_NE(r.output.find("unknown command 'dojo nonsense'"), std::string::npos) << r.output;
  r = test::run_dojo("--threads 1 lam trian --help");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_NE(r.output.find("'dojo lam trian' (did you mean 'dojo lam train'?)"), std::string::npos)
      << r.output;
  // Real commands still parse: a value after an option is not a command word.
  r = test::run_dojo("--threads 1 version --json");
  EXPECT_EQ(r.exit_code, 0) << r.output;
  r = test::run_dojo("wm rollout --help");
  EXPECT_EQ(r.exit_code, 0) << r.output;
}

// The shared options carry one name, alias and help text on every command that takes them
// (src/cli/options.cpp holds the table these strings come from).
TEST(Cli, SharedOptionsReadTheSameEverywhere) {
  const std::map<std::string, std::pair<std::string, std::string>> shared = {
      {"--data", {"-d,--data", "Dataset directory (episode store, LeRobot, EgoDex or video folder)"}},
      {"--split", {"-s,--split", "Dataset split (train, val, ..., or all)"}},
      {"--seed", {"--seed", "Random seed: the same seed gives the same result"}},
      {"--device", {"--device", "Where the networks run: cpu | cuda | cuda:N | auto"}},
      {"--precision", {"--precision", "fp32 | bf16 | fp16 (CUDA only)"}},
      {"--json", {"--json", "Print the result as JSON"}},
      {"--workers", {"-j,--workers", "Worker threads for data generation and loading (0 = all cores)"}},
      {"--out", {"-o,--out", "Output:"}},
      {"--checkpoint", {"-c,--checkpoint,--ckpt", "Checkpoint directory:"}}};
  const std::vector<std::pair<std::string, std::vector<std::string>>> commands = {
      {"eval", {"--data", "--split", "--seed", "--device", "--precision", "--json", "--out", "--checkpoint"}},
      {"wm train", {"--data", "--split", "--seed", "--device", "--precision", "--out"}},
      {"wm rollout", {"--data", "--split", "--seed", "--device", "--out", "--checkpoint"}},
      {"tokenizer train", {"--data", "--split", "--seed", "--workers", "--out"}},
      {"tokenizer eval", {"--data", "--split", "--seed", "--json", "--out", "--checkpoint"}},
      {"lam train", {"--seed", "--workers", "--out"}},
      {"lam probe", {"--data", "--json", "--checkpoint"}},
#ifdef DOJO_WITH_SIM
      {"sim generate", {"--seed", "--workers", "--json", "--out"}},
#endif
      {"data info", {"--json"}},
      {"bench", {"--device", "--json"}}};
  for (const auto& [command, options] : commands) {
    const auto r = test::run_dojo(command + " --help");
    ASSERT_EQ(r.exit_code, 0) << command;
    // "  NAMES TYPE  HELP" on one line, or HELP on the next when the names are long.
    for (const auto& option : options) {
      const auto& [names, help] = shared.at(option);
      std::istringstream lines(r.output);
      std::string line, next;
      bool found = false;
      while (std::getline(lines, line))
        if (line.find("  " + names + " ") != std::string::npos)
          found = line.find(help) != std::string::npos ||
                  (std::getline(lines, next) && next.find(help) != std::string::npos);
      EXPECT_TRUE(found) << "`dojo " << command << " --help` lacks \"" << names << " ... " << help << "\":\n"
                         << r.output;
    }
  }
}

#ifdef DOJO_WITH_SIM
// `sim generate --policies`: the built-in set by name, a file's scripted policies in turn, and a
// policy the simulator cannot run refused in one line naming the file and the policy.
TEST(Cli, SimGenerateRunsAPolicySetInTurn) {
  test::TempDir tmp;
  const std::string common =
      "sim generate --embodiment robot --episodes 2 --frames 12 --size 32x32 --workers 1";
  auto r = test::run_dojo(common + " --policies default --out " + (tmp / "set").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto policy = [&](const std::string& dir, int episode) {
    return nlohmann::json::parse(
               test::read_file(tmp / dir / "episodes" / ("00000" + std::to_string(episode)) / "meta.json"))
        .at("policy")
        .get<std::string>();
  };
  EXPECT_EQ(policy("set", 0), "expert");  // the first two of the built-in set
  EXPECT_EQ(policy("set", 1), "good");
  std::ofstream(tmp / "mine.json")
      << R"({"policies": [{"name": "still", "behavior": "idle"}, {"name": "shaky", "quality": {"noise_std": 0.1}}]})";
  r = test::run_dojo(common + " --val-fraction 0 --policies " + (tmp / "mine.json").string() + " --out " +
                     (tmp / "mine").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(policy("mine", 0), "still");
  EXPECT_EQ(policy("mine", 1), "shaky");
  std::ofstream(tmp / "remote.json") << R"({"policies": [{"name": "remote", "command": "true"}]})";
  r = test::run_dojo(common + " --policies " + (tmp / "remote.json").string() + " --out " +
                     (tmp / "r").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("remote.json: policy 'remote' is not scripted"), std::string::npos) << r.output;
  EXPECT_EQ(std::count(r.output.begin(), r.output.end(), '\n'), 1) << r.output;
}
#endif

TEST(Cli, NoCommandFails) {
  const auto result = test::run_dojo("");
  EXPECT_NE(result.exit_code, 0);
}

}  // namespace dojo
