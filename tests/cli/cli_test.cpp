// End-to-end checks of the `dojo` executable: help, version JSON, bad usage.
#include <nlohmann/json.hpp>

#include "test_util.h"

namespace dojo {

TEST(Cli, HelpListsCommands) {
  const auto result = test::run_dojo("--help");
  EXPECT_EQ(result.exit_code, 0);
  for (const char* name : {"version", "ckpt", "video", "bench"})
    EXPECT_NE(result.output.find(name), std::string::npos) << name;
}

TEST(Cli, VersionJson) {
  const auto result = test::run_dojo("--threads 2 version --json");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto info = nlohmann::json::parse(result.output);
  EXPECT_EQ(info["threads"], 2);
  EXPECT_EQ(info["git_commit"].get<std::string>().empty(), false);
  EXPECT_TRUE(info["cuda_available"].is_boolean());
}

TEST(Cli, UnknownCommandFailsWithUsageError) {
  const auto result = test::run_dojo("frobnicate");
  EXPECT_NE(result.exit_code, 0);
  EXPECT_EQ(result.output.find("terminate"), std::string::npos);
}

TEST(Cli, NoCommandFails) {
  const auto result = test::run_dojo("");
  EXPECT_NE(result.exit_code, 0);
}

}  // namespace dojo
