// A released DiT, converted from the file PyTorch wrote, served on a LeRobot GR-1 set that names no
// robot: with the robot named, clients send commands in GR-1's own 29 units (normalised with the
// dataset's statistics, since a converted model records no range) and get video back; without it
// the server says what a command is not.
#include <boost/beast/http.hpp>

#include <nlohmann/json.hpp>

#include "data/lerobot_writer.h"
#include "http_request.h"
#include "models/released_import.h"
#include "serve/model_host.h"
#include "serve/server.h"
#include "sessions_drained.h"
#include "test_util.h"

namespace dojo::serve {
namespace {

namespace http = boost::beast::http;

TEST(ReleasedServe, ConvertedDitStreamsALeRobotSetInTheRobotsUnits) {
  test::OneThread one;
  test::TempDir tmp;
  models::ImportOptions fp32;
  fp32.dtype = torch::kFloat32;
  models::import_released(test::torch_files_dir() / "dit_action384_ema_bf16.pt", tmp / "dit", fp32);
  models::import_released(test::torch_files_dir() / "wan_vae.pth", tmp / "vae", {});
  data::lerobot_fixture::Fixture fx;
  fx.robot_type = "";  // the robot is named by the server's options alone
  const auto lerobot = data::lerobot_fixture::make_lerobot(tmp / "gr1_set", fx);

  auto host_for = [&](const std::string& embodiment) {
    ModelHost::Options o;
    ModelSpec student;
    student.name = "released";
    student.checkpoint = tmp / "dit";
    student.tokenizer = tmp / "vae";
    o.models = {student};
    o.data = lerobot;
    o.split = "train";
    o.open.embodiment = embodiment;
    auto host = std::make_shared<ModelHost>(o);
    host->load();
    return host;
  };
  ServeOptions so;
  so.port = 0;
  so.recordings = tmp / "recordings";
  nlohmann::json body = {{"format", "jpeg"}, {"actions", nlohmann::json::array()}};
  for (int i = 0; i < 8; ++i) {
    std::vector<float> row(29);
    for (int d = 0; d < 29; ++d) row[d] = data::lerobot_fixture::raw_action(0, 2 * (i + 1), d);
    body["actions"].push_back(row);
  }
  {
    Server server(so, host_for("gr1"));
    const auto port = server.start();
    const auto caps =
        nlohmann::json::parse(test::http_request(port, http::verb::get, "/api/capabilities").body);
    EXPECT_EQ(caps["embodiments"], nlohmann::json::array({"gr1"}));
    EXPECT_EQ(caps["models"][0]["action_slots"][0]["width"], 29);
    EXPECT_EQ(caps["frame_height"], 32);
    EXPECT_EQ(caps["frame_width"], 32);
    auto r = test::http_request(port, http::verb::post, "/v1/rollout", body.dump());
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(nlohmann::json::parse(r.body).at("frames").size(), 9u) << "the start frame and 8 more";
    auto narrow = body;
    for (auto& row : narrow["actions"]) row.erase(28);
    r = test::http_request(port, http::verb::post, "/v1/rollout", narrow.dump());
    EXPECT_EQ(r.status, 400);
    EXPECT_NE(r.body.find("or 29 (raw commands)"), std::string::npos) << r.body;
    ASSERT_TRUE(test::sessions_drained(server));
    server.stop();
  }
  {
    // Unnamed, the set's actions are no robot's: raw commands are refused, not guessed.
    Server server(so, host_for("auto"));
    const auto port = server.start();
    const auto r = test::http_request(port, http::verb::post, "/v1/rollout", body.dump());
    EXPECT_EQ(r.status, 400);
    EXPECT_NE(r.body.find("rows must have 384 values"), std::string::npos) << r.body;
    server.stop();
  }
}

}  // namespace
}  // namespace dojo::serve
