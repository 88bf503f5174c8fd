// docs/new_robot.md, capped: a robot the engine has not seen (a LeRobot set the exporter writes
// under a new robot_type), named in an embodiment table; LoRA post-training from the reference
// world model, evaluation on its held-out episodes, and a teleoperation server whose page drives
// it in its own units. Without the table every command says how to name it.
#include <boost/beast/http.hpp>

#include <fstream>
#include <nlohmann/json.hpp>

#include "data/embodiments.h"
#include "http_request.h"
#include "serve/model_host.h"
#include "serve/server.h"
#include "sessions_drained.h"
#include "synthetic_data.h"
#include "test_util.h"

namespace dojo::serve {
namespace {

namespace http = boost::beast::http;

TEST(NewRobot, ATableNamesItLoraAdaptsTheReferenceModelAndTheServerDrivesIt) {
  test::OneThread one;
  test::TempDir tmp;
  test::SyntheticOptions g;
  g.episodes = 4;
  g.val_episodes = 1;
  g.frames = 40;
  g.size = 64;  // the reference tokenizer's frames
  test::write_synthetic_dataset(tmp / "sim", g);
  const auto lerobot = tmp / "acme_set";
  auto r = test::run_dojo("data convert " + (tmp / "sim").string() + " " + lerobot.string() +
                          " --to lerobot --robot-type acme_arm_v1");
  ASSERT_EQ(r.exit_code, 0) << r.output;

  nlohmann::json action = nlohmann::json::array();
  for (const char* key : {"y", "x", "a", "b", "c", "d"}) action.push_back({key, 1});
  const auto table = tmp / "robots.json";
  std::ofstream(table) << nlohmann::json{{"embodiments",
                                          {{{"name", "acme_arm"},
                                            {"robot_types", {"acme_arm_v1"}},
                                            {"slot", {220, 226}},
                                            {"action", action}}}}}
                              .dump();
  const auto reference = std::filesystem::path(DOJO_SOURCE_DIR) / "models" / "reference";
  const std::string tok = " --tokenizer " + (reference / "tokenizer").string();
  const std::string with_table = "--threads 1 --embodiments " + table.string() + " ";

  // Unnamed, the set's actions fill no slot: refused with the way to name the robot.
  r = test::run_dojo("--threads 1 wm train --stage posttrain --init " +
                     (reference / "wm_posttrain").string() + " --data " + lerobot.string() + tok +
                     " --steps 1 --out " + (tmp / "x").string());
  EXPECT_NE(r.exit_code, 0);
  EXPECT_NE(r.output.find("--embodiments FILE"), std::string::npos) << r.output;

  r = test::run_dojo(with_table + "wm train --stage posttrain --init " +
                     (reference / "wm_posttrain").string() + " --data " + lerobot.string() + tok +
                     " --lora 4 --steps 3 --batch 2 --hop 8 --save-every 3 --out " +
                     (tmp / "acme_wm").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto checkpoint = tmp / "acme_wm" / "checkpoint";
  const auto config = nlohmann::json::parse(test::read_file(checkpoint / "config.json"));
  EXPECT_TRUE(config.at("actions").contains("acme_arm")) << "a new slot: its range recorded";
  EXPECT_TRUE(std::filesystem::exists(checkpoint / "adapter_model.safetensors"));

  r = test::run_dojo(with_table + "eval --checkpoint " + checkpoint.string() + tok + " --data " +
                     lerobot.string() + " --split val --episodes 1 --chunks 1 --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const auto report = nlohmann::json::parse(r.output.substr(r.output.find("\n{") + 1));  // after the log
  const auto data = report.at("splits").at(0).at("data").get<std::string>();
  EXPECT_NE(data.find("slot acme_arm (6 actions), model normalisation"), std::string::npos) << data;
  r = test::run_dojo("--threads 1 eval --checkpoint " + checkpoint.string() + tok + " --data " +
                     lerobot.string() + " --split val --episodes 1 --chunks 1 --json");
  EXPECT_NE(r.exit_code, 0) << "a model of a robot nobody named";
  EXPECT_NE(r.output.find("acme_arm"), std::string::npos) << r.output;

  // The server, as `dojo --embodiments robots.json serve` runs it.
  data::load_embodiment_table(table);
  ModelHost::Options o;
  ModelSpec model;
  model.name = "teacher";
  model.streaming = false;  // `serve --teacher`, as the guide serves it
  model.checkpoint = checkpoint;
  model.tokenizer = reference / "tokenizer";
  o.models = {model};
  o.data = lerobot;
  o.split = "val";
  auto host = std::make_shared<ModelHost>(o);
  host->load();
  ServeOptions so;
  so.port = 0;
  so.recordings = tmp / "recordings";
  Server server(so, host);
  const auto port = server.start();
  const auto caps =
      nlohmann::json::parse(test::http_request(port, http::verb::get, "/api/capabilities").body);
  EXPECT_EQ(caps["embodiments"], nlohmann::json::array({"acme_arm"})) << caps.dump();
  EXPECT_EQ(caps["models"][0]["action_slots"][0]["width"], 6) << caps.dump();
  auto page = test::http_request(port, http::verb::get, "/");
  EXPECT_EQ(page.status, 200);
  // The page's controls for the new robot: one per dimension, on keys.
  page = test::http_request(port, http::verb::get, "/acme_arm.mapping.json");
  ASSERT_EQ(page.status, 200) << page.body;
  const auto mapping = nlohmann::json::parse(page.body);
  ASSERT_EQ(mapping.at("dims").size(), 6u);
  EXPECT_EQ(mapping["dims"][0]["keys"], nlohmann::json::array({"KeyA", "KeyD"}));
  // Raw commands in the robot's 6 units drive a rollout.
  nlohmann::json body = {{"format", "jpeg"}, {"actions", nlohmann::json::array()}};
  for (int i = 0; i < 12; ++i) body["actions"].push_back(std::vector<float>(6, 0.05f * i));
  const auto rollout = test::http_request(port, http::verb::post, "/v1/rollout", body.dump());
  ASSERT_EQ(rollout.status, 200) << rollout.body;
  EXPECT_EQ(nlohmann::json::parse(rollout.body).at("frames").size(), 13u) << "the start frame and a chunk";
  ASSERT_TRUE(test::sessions_drained(server));
  server.stop();
}

}  // namespace
}  // namespace dojo::serve
