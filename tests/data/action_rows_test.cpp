#include "data/action_rows.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include <nlohmann/json.hpp>

#include "core/error.h"
#include "test_util.h"

namespace dojo::data {
namespace {

TEST(ActionRows, OneParserForEveryEntryPoint) {
  const auto rows = action_rows_from_json(nlohmann::json::parse("[[1, 2.5], [-3, 4e3]]"), "x");
  EXPECT_TRUE(rows.equal(torch::tensor({1.0f, 2.5f, -3.0f, 4000.0f}).view({2, 2})));
  const std::vector<std::pair<std::string, std::string>> bad = {
      {"[]", "x must be a non-empty array of rows (at most 2)"},
      {"{\"a\": 1}", "x must be a non-empty array of rows (at most 2)"},
      {"[[]]", "x: every row must be an array of numbers"},
      {"[[1, 2], [3]]", "x: every row must have 2 values"},
      {"[[1, \"2\"]]", "x: values must be finite numbers"},
      {"[[1], [2], [3]]", "x must be a non-empty array of rows (at most 2)"},
  };
  for (const auto& [text, message] : bad)
    EXPECT_EQ(test::error_message([&] { action_rows_from_json(nlohmann::json::parse(text), "x", 2); }),
              message)
        << text;
}

}  // namespace
}  // namespace dojo::data
