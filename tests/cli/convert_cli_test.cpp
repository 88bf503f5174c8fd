// `dojo convert`: a released checkpoint into a checkpoint directory that the other commands load;
// one-line errors and a non-zero exit for files it refuses.
#include <filesystem>
#include <nlohmann/json.hpp>

#include "core/checkpoint.h"
#include "test_util.h"

namespace dojo {
namespace {

TEST(ConvertCli, DcpFolderToACheckpointTheEngineLoads) {
  test::TempDir dir;
  const auto result = test::run_dojo("convert " + (test::dcp_fixture_dir() / "checkpoints").string() + " " +
                                     (dir / "dit").string() + " --dtype bf16 --json");
  ASSERT_EQ(result.exit_code, 0) << result.output;
  const auto report = nlohmann::json::parse(result.output.substr(result.output.find('{')));
  EXPECT_EQ(report["model"], "action_dit");
  EXPECT_EQ(report["format"], "dcp");
  EXPECT_EQ(report["weights"], "net_ema");
  EXPECT_EQ(report["skipped"], 64);  // the 64 net.* tensors
  const auto ckpt = Checkpoint::open(dir / "dit");
  EXPECT_EQ(ckpt.model().info("net.blocks.0.self_attn.q_proj.weight").dtype, "BF16");
  EXPECT_EQ(ckpt.model().info("net.pos_embedder.seq").dtype, "F32");  // buffers keep their dtype
  const auto info = test::run_dojo("ckpt info " + (dir / "dit").string() + " --json");
  EXPECT_EQ(info.exit_code, 0) << info.output;
}

TEST(ConvertCli, RefusedFilesExitNonZeroWithOneLine) {
  test::TempDir dir;
  const auto evil = test::run_dojo("convert " + (test::torch_files_dir() / "evil_os_system.pt").string() +
                                   " " + (dir / "out").string());
  EXPECT_EQ(evil.exit_code, 1) << evil.output;
  EXPECT_NE(evil.output.find("refuses global 'posix.system'"), std::string::npos) << evil.output;
  EXPECT_FALSE(std::filesystem::exists(test::torch_files_marker()));
  EXPECT_FALSE(std::filesystem::exists(dir / "out"));
  const auto missing =
      test::run_dojo("convert " + (dir / "nothing.pt").string() + " " + (dir / "out").string());
  EXPECT_EQ(missing.exit_code, 1);
  EXPECT_NE(missing.output.find("nothing.pt"), std::string::npos) << missing.output;
  const auto usage = test::run_dojo("convert a b --model gpt");
  EXPECT_EQ(usage.exit_code, 2) << usage.output;
}

}  // namespace
}  // namespace dojo
