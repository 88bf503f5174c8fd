#include "core/dcp.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "core/error.h"
#include "core/safetensors.h"
#include "test_util.h"

namespace dojo {
namespace {

namespace fs = std::filesystem;

fs::path model_dir() { return test::dcp_fixture_dir() / "checkpoints" / "iter_000000010" / "model"; }

// The golden weight a fixture key holds ("net." or "net_ema." + the golden name).
torch::Tensor golden_weight(const SafetensorsFile& golden, const std::string& rest) {
  return golden.contains("net." + rest) ? golden.tensor("net." + rest) : golden.tensor(rest);
}

TEST(Dcp, EveryReleasedFolderFormResolvesToTheModelFolder) {
  const auto fixture = test::dcp_fixture_dir();
  for (const fs::path& form :
       {fixture / "checkpoints", fixture / "checkpoints" / "iter_000000010", model_dir()}) {
    EXPECT_TRUE(DcpCheckpoint::is_dcp(form)) << form;
    EXPECT_EQ(DcpCheckpoint::resolve(form), model_dir()) << form;
  }
  EXPECT_FALSE(DcpCheckpoint::is_dcp(fixture));
  EXPECT_NE(
      test::error_message([&] { DcpCheckpoint::resolve(fixture); }).find("not a distributed checkpoint"),
      std::string::npos);
  test::TempDir tmp;
  std::ofstream(tmp / "latest_checkpoint.txt") << "iter_000000099.pt\n";
  EXPECT_NE(test::error_message([&] { DcpCheckpoint::resolve(tmp.path()); }).find("names 'iter_000000099'"),
            std::string::npos);
}

TEST(Dcp, ShardsReassembleIntoTheGoldenWeights) {
  const DcpCheckpoint dcp = DcpCheckpoint::open(test::dcp_fixture_dir() / "checkpoints");
  const auto golden = SafetensorsFile::open(test::golden_dir() / "dit_tiny_weights.safetensors");
  const auto expected = nlohmann::json::parse(test::read_file(test::dcp_fixture_dir() / "EXPECTED.json"));
  size_t ema = 0, trained = 0, sharded = 0;
  for (const auto& entry : dcp.tensors()) {
    const torch::Tensor t = dcp.tensor(entry);
    sharded += entry.chunks.size() > 1;
    if (entry.name.rfind("net_ema.", 0) == 0) {
      const std::string rest = entry.name.substr(8);
      EXPECT_TRUE(torch::equal(t, golden_weight(golden, rest))) << entry.name;
      const auto& e = expected["keys"]["net." + rest];
      EXPECT_EQ(t.sizes().vec(), e["shape"].get<std::vector<int64_t>>()) << entry.name;
      EXPECT_NEAR(t.to(torch::kFloat64).sum().item<double>(), e["sum_f32"].get<double>(),
                  1e-4 * (1 + std::abs(e["sum_f32"].get<double>())))
          << entry.name;
      ++ema;
    } else {
      const torch::Tensor g = golden_weight(golden, entry.name.substr(4));
      EXPECT_TRUE(torch::equal(t, g.is_floating_point() ? g * 0.5 : g)) << entry.name;
      ++trained;
    }
  }
  EXPECT_EQ(ema, expected["keys"].size());
  EXPECT_EQ(trained, ema);
  EXPECT_GT(sharded, ema);  // every tensor of one or more dimensions was split across the 2 ranks
}

TEST(Dcp, DamagedCopiesNameWhatIsWrong) {
  test::TempDir tmp;
  const auto copy = tmp / "model";
  fs::copy(model_dir(), copy);
  for (const auto& f : fs::directory_iterator(copy))
    fs::permissions(f.path(), fs::perms::owner_all, fs::perm_options::add);
  {  // a rank's file cut short
    const auto rank1 = copy / "__1_0.distcp";
    fs::resize_file(rank1, fs::file_size(rank1) / 2);
    const DcpCheckpoint dcp = DcpCheckpoint::open(copy);
    std::string message;
    for (const auto& entry : dcp.tensors()) {
      message = test::error_message([&] { dcp.tensor(entry); });
      if (message != "(no error)") break;
    }
    EXPECT_NE(message.find("__1_0.distcp"), std::string::npos) << message;
  }
  {  // a rank's file missing
    fs::remove(copy / "__1_0.distcp");
    const DcpCheckpoint dcp = DcpCheckpoint::open(copy);
    EXPECT_NE(test::error_message([&] {
                dcp.tensor(*dcp.find("net.blocks.0.self_attn.q_proj.weight"));
              }).find("__1_0.distcp"),
              std::string::npos);
  }
  {  // metadata that runs a command
    fs::copy_file(test::torch_files_dir() / "evil_metadata.pkl", copy / ".metadata",
                  fs::copy_options::overwrite_existing);
    EXPECT_NE(test::error_message([&] { DcpCheckpoint::open(copy); }).find("refuses global 'posix.system'"),
              std::string::npos);
  }
}

}  // namespace
}  // namespace dojo
