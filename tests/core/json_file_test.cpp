// JSON files and config fields: errors name the file or the field; unmeasured numbers read as null.
#include "core/json_file.h"

#include <cmath>
#include <limits>

#include "core/atomic_file.h"
#include "core/error.h"
#include "test_util.h"

namespace dojo {
namespace {

TEST(JsonFile, ReadErrorsNameTheFile) {
  test::TempDir dir;
  write_file_atomic(dir / "good.json", std::string(R"({"a": 1})"));
  EXPECT_EQ(read_json_file(dir / "good.json").at("a"), 1);
  write_file_atomic(dir / "bad.json", std::string("{\"a\": "));
  EXPECT_NE(test::error_message([&] {
              read_json_file(dir / "bad.json");
            }).find((dir / "bad.json").string() + ": invalid JSON"),
            std::string::npos);
  EXPECT_NE(test::error_message([&] { read_json_file(dir / "none.json"); }).find("none.json: cannot open"),
            std::string::npos);
}

TEST(JsonFile, FieldsKeepAbsentValuesAndNameWrongTypes) {
  const auto j = nlohmann::json::parse(R"({"steps": 3, "lr": 0.5, "on": true, "bad": "x"})");
  const JsonFields fields(j, "run.json");
  int64_t steps = 0, absent = 7;
  double lr = 0;
  bool on = false;
  fields.get("steps", steps);
  fields.get("lr", lr);
  fields.get("on", on);
  fields.get("missing", absent);
  EXPECT_EQ(steps, 3);
  EXPECT_EQ(lr, 0.5);
  EXPECT_TRUE(on);
  EXPECT_EQ(absent, 7);
  EXPECT_EQ(test::error_message([&] { fields.get("bad", steps); }),
            "run.json: field 'bad' must be an integer");
  EXPECT_EQ(test::error_message([&] { fields.get("lr", steps); }), "run.json: field 'lr' must be an integer");
  EXPECT_EQ(test::error_message([&] { JsonFields(nlohmann::json::array(), "list.json"); }),
            "list.json: expected a JSON object");
  EXPECT_EQ(test::error_message([&] { check_positive("run.json", "steps", 0); }),
            "run.json: field 'steps' must be positive, got 0");
}

TEST(JsonFile, UnmeasuredNumbersAreNull) {
  EXPECT_EQ(finite_or_null(2.5), nlohmann::json(2.5));
  EXPECT_EQ(finite_or_null(0.0), nlohmann::json(0.0));
  EXPECT_TRUE(finite_or_null(std::nan("")).is_null());
  EXPECT_TRUE(finite_or_null(std::numeric_limits<double>::infinity()).is_null());
  EXPECT_TRUE(finite_or_null(-std::numeric_limits<double>::infinity()).is_null());
  // What a report writes parses back.
  const nlohmann::json report = {{"a", finite_or_null(std::nan(""))}, {"b", finite_or_null(1.0)}};
  EXPECT_EQ(nlohmann::json::parse(report.dump()), report);
}

}  // namespace
}  // namespace dojo
