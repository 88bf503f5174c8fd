// The reference set's real-time student (<ref>/student) and fast streaming decoder
// (<ref>/fast_decoder): `wm stream`, `eval --student`, `serve` and `policy eval` use them with no
// model arguments, and keep their former defaults and messages where the set has no student. The
// set is a temporary one named by DOJO_REFERENCE: the shipped tokenizer, probe and post-trained
// world model, that world model again as the "student" (its config.json with a one-hop "student"
// entry), and a random fast decoder.
#include <gtest/gtest.h>

#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <thread>

#include "core/checkpoint.h"
#include "models/fast_decoder.h"
#include "serve/http_request.h"
#include "synthetic_data.h"
#include "test_util.h"

extern char** environ;

namespace dojo {
namespace {

namespace fs = std::filesystem;

const fs::path kShipped = fs::path(DOJO_SOURCE_DIR) / "models" / "reference";

// TMP/reference: a reference set with a student and a fast decoder (either removable), and
// TMP/robot: a small dataset. Commands run in TMP, which holds no `dojo_demo`.
class ReferenceStudent : public ::testing::Test {
 protected:
  void SetUp() override {
    for (const char* member : {"tokenizer", "probe", "wm_posttrain"})
      fs::create_directory_symlink(kShipped / member, ref_ / member);
    fs::create_directories(student());
    fs::create_symlink(kShipped / "wm_posttrain" / "model.safetensors", student() / "model.safetensors");
    auto config = nlohmann::json::parse(test::read_file(kShipped / "wm_posttrain" / "config.json"));
    config["student"] = {{"window_frames", 3}, {"sink_frames", 1}, {"steps", 1}};
    std::ofstream(student() / "config.json") << config.dump(2);
    models::FastDecoderConfig c;
    c.widths = {16, 12, 8};
    c.blocks = {1, 1, 1};
    c.head_width = 8;
    torch::manual_seed(0);
    save_checkpoint(fast_decoder(), models::fast_decoder_checkpoint(*models::FastDecoder(c)));
  }

  fs::path student() const { return ref_ / "student"; }
  fs::path fast_decoder() const { return ref_ / "fast_decoder"; }

  // `dojo --threads 1 ARGS` in TMP with DOJO_REFERENCE=TMP/reference.
  test::CommandResult dojo(const std::string& args) const {
    return test::run_command("cd " + tmp_.path().string() + " && DOJO_REFERENCE=" + ref_.string() + " " +
                             DOJO_EXE + " --threads 1 " + args);
  }
  std::string data() {
    if (!fs::exists(tmp_ / "robot")) {
      test::SyntheticOptions g;
      g.episodes = 1;
      g.frames = 52;  // `wm stream` replays 4 chunks of the recorded actions
      g.size = 64;
      test::write_synthetic_dataset(tmp_ / "robot", g);
    }
    return " --data " + (tmp_ / "robot").string() + " --split all";
  }

  test::OneThread one_;
  test::TempDir tmp_;
  fs::path ref_ = (fs::create_directories(tmp_ / "reference"), tmp_ / "reference");
};

// The JSON object a command printed after its log lines.
nlohmann::json printed_json(const test::CommandResult& r) {
  const auto start = r.output.find("{\n");
  return start == std::string::npos ? nlohmann::json() : nlohmann::json::parse(r.output.substr(start));
}

TEST_F(ReferenceStudent, StreamAndEvalUseTheStudentAndItsFastDecoder) {
  auto r = dojo("wm stream" + data() + " --frames 8 --json --out " + (tmp_ / "s.mp4").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  auto summary = printed_json(r);
  EXPECT_EQ(summary.at("checkpoint"), student().string()) << r.output;
  EXPECT_EQ(summary.at("student_steps"), 1) << "the student's own settings";
  EXPECT_EQ(summary.at("decoder"), "fast");
  EXPECT_EQ(summary.at("fast_decoder"), fast_decoder().string());
  EXPECT_TRUE(fs::exists(tmp_ / "s.mp4"));

  r = dojo("eval --student" + data() + " -n 1 --chunks 1 --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto metrics = printed_json(r);
  EXPECT_EQ(metrics.at("checkpoint"), student().string()) << r.output;
  EXPECT_EQ(metrics.at("tokenizer"), (ref_ / "tokenizer").string());
  EXPECT_EQ(metrics.at("fast_decoder"), fast_decoder().string());
  EXPECT_EQ(metrics.at("sampler").at("student").at("steps"), 1);

  // A tokenizer given (here the set's own path, but it could be another's) takes no decoder of the set.
  r = dojo("wm stream" + data() + " --frames 4 --no-decode --json --tokenizer " +
           (ref_ / "tokenizer").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(printed_json(r).at("decoder"), "wan") << r.output;

  // Without a student: the set's world model streams, as before.
  fs::remove_all(student());
  fs::remove_all(fast_decoder());
  r = dojo("wm stream" + data() + " --frames 4 --no-decode --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  summary = printed_json(r);
  EXPECT_EQ(summary.at("checkpoint"), (ref_ / "wm_posttrain").string()) << r.output;
  EXPECT_EQ(summary.at("decoder"), "wan");
  r = dojo("eval --student" + data() + " -n 1 --chunks 1 --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(printed_json(r).at("checkpoint"), (ref_ / "wm_posttrain").string()) << r.output;
}

#ifdef DOJO_WITH_SIM

namespace http = boost::beast::http;

// `dojo serve` with no model arguments: the set's student (fast decoder) and teacher on held-out
// DojoSim episodes made on the spot; a rollout starts from the first of them.
TEST_F(ReferenceStudent, ServeWithNoArgumentsServesTheSetOnDojoSimScenes) {
  const auto log = tmp_ / "serve.log";
  // The child's arguments and environment, made before fork (the child only execs).
  const std::string exe = DOJO_EXE, reference = "DOJO_REFERENCE=" + ref_.string();
  std::vector<std::string> args = {exe, "--threads", "1", "serve", "--port", "0"};
  std::vector<char*> argv, envp;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  for (char** e = environ; *e != nullptr; ++e)
    if (std::string(*e).rfind("DOJO_REFERENCE=", 0) != 0) envp.push_back(*e);
  envp.push_back(const_cast<char*>(reference.c_str()));
  envp.push_back(nullptr);
  const int out = open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  ASSERT_GE(out, 0);
  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    if (chdir(tmp_.path().c_str()) != 0) _exit(127);
    dup2(out, 1);
    dup2(out, 2);
    execve(exe.c_str(), argv.data(), envp.data());
    _exit(127);
  }
  close(out);

  // Ready (the DojoSim episodes made and the models loaded) within 3 minutes, or exited.
  bool ready = false, exited = false;
  int status = 0;
  for (int i = 0; i < 1800 && !ready && !exited; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    ready = test::read_file(log).find("serve: ready") != std::string::npos;
    exited = waitpid(pid, &status, WNOHANG) == pid;
  }
  std::string text = test::read_file(log);
  if (!ready) {
    if (!exited) kill(pid, SIGKILL), waitpid(pid, &status, 0);
    FAIL() << "the server never became ready:\n" << text;
  }
  const std::string listening = "listening on http://127.0.0.1:";
  const auto at = text.find(listening);
  ASSERT_NE(at, std::string::npos) << text;
  const auto port = static_cast<uint16_t>(std::stoi(text.substr(at + listening.size())));

  const auto capabilities = test::http_request(port, http::verb::get, "/api/capabilities");
  ASSERT_EQ(capabilities.status, 200) << capabilities.body;
  const auto caps = nlohmann::json::parse(capabilities.body);
  ASSERT_EQ(caps.at("models").size(), 2u) << caps.dump();
  EXPECT_EQ(caps["models"][0].at("name"), "student");
  EXPECT_EQ(caps["models"][0].at("kind"), "student");
  EXPECT_EQ(caps["models"][0].at("decoder"), "fast");
  EXPECT_EQ(caps["models"][1].at("name"), "teacher");
  EXPECT_EQ(caps.at("embodiments"), nlohmann::json::array({"dojosim_robot"}));
  EXPECT_EQ(caps.at("frame_size"), 64);
  ASSERT_EQ(caps.at("episodes").size(), 8u) << "the held-out DojoSim episodes";
  const auto rolled = test::http_request(
      port, http::verb::post, "/v1/rollout",
      R"({"actions": [[0,0,0,0,0,0],[0,0,0,0,0,0],[0,0,0,0,0,0],[0,0,0,0,0,0]], "format": "jpeg"})");
  ASSERT_EQ(rolled.status, 200) << rolled.body;
  const auto rollout = nlohmann::json::parse(rolled.body);
  EXPECT_EQ(rollout.at("episode"), caps["episodes"][0]);
  EXPECT_EQ(rollout.at("frames").size(), 5u) << "the start frame and one step's 4";

  kill(pid, SIGTERM);
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << test::read_file(log);
  text = test::read_file(log);
  EXPECT_NE(text.find("model 'student' loaded from " + student().string()), std::string::npos) << text;
  EXPECT_NE(text.find("model 'teacher' loaded from " + (ref_ / "wm_posttrain").string()), std::string::npos)
      << text;

  // Without a student (and no dojo_demo here): today's refusal, one line.
  fs::remove_all(student());
  const auto r = dojo("serve --port 0");
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("error: serve: no tokenizer (give --tokenizer, or --demo DIR"), std::string::npos)
      << r.output;
}

// `policy detector --world-model` and `policy eval` replay in the set's student with its fast
// decoder when no world model is named; without a student they look for the demo's, as before.
TEST_F(ReferenceStudent, PolicyEvaluationUsesTheStudent) {
  std::ofstream(tmp_ / "set.json")
      << R"({"policies": [{"name": "expert"}, {"name": "idle", "behavior": "idle"}]})";
  const std::string set = " --policies " + (tmp_ / "set.json").string();
  auto r = dojo("policy detector --world-model --scenes 2 --steps 10" + set + " --out det");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto made = nlohmann::json::parse(test::read_file(tmp_ / "det" / "data.json"));
  EXPECT_EQ(made.at("frames").at("world_model").at("path"), student().string());
  EXPECT_EQ(made.at("frames").at("tokenizer").at("path"), (ref_ / "tokenizer").string());
  EXPECT_EQ(made.at("frames").at("fast_decoder").at("path"), fast_decoder().string());

  r = dojo("policy eval --no-bc --scenes 1 --videos 0 --detector det --frames 8 --settle-frames 4" + set +
           " --out pe");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto report = nlohmann::json::parse(test::read_file(tmp_ / "pe" / "report.json"));
  EXPECT_EQ(report.at("world_model"), "student");
  EXPECT_EQ(report.at("fingerprint").at("world_model").at("path"), student().string());
  EXPECT_EQ(report.at("fingerprint").at("fast_decoder").at("path"), fast_decoder().string());

  fs::remove_all(student());
  r = dojo("policy eval --no-bc --out pe2");
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_NE(r.output.find("error: policy eval: no world model at dojo_demo/student/checkpoint"),
            std::string::npos)
      << r.output;
}

#endif  // DOJO_WITH_SIM

}  // namespace
}  // namespace dojo
