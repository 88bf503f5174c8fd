#include "core/json_file.h"

#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>

#include "core/error.h"

namespace dojo {

nlohmann::json read_json_file(const std::filesystem::path& path) {
  std::ifstream in(path);
  if (!in) throw Error(path.string() + ": cannot open: " + std::strerror(errno));
  try {
    return nlohmann::json::parse(in);
  } catch (const nlohmann::json::exception& e) {
    throw Error(path.string() + ": invalid JSON: " + e.what());
  }
}

JsonFields::JsonFields(const nlohmann::json& j, std::string what) : j_(j), what_(std::move(what)) {
  DOJO_CHECK(j_.is_object(), what_ + ": expected a JSON object");
}

void JsonFields::get(const char* key, int64_t& v) const {
  if (!j_.contains(key)) return;
  DOJO_CHECK(j_[key].is_number_integer(), what_ + ": field '" + key + "' must be an integer");
  v = j_[key].get<int64_t>();
}

void JsonFields::get(const char* key, double& v) const {
  if (!j_.contains(key)) return;
  DOJO_CHECK(j_[key].is_number(), what_ + ": field '" + key + "' must be a number");
  v = j_[key].get<double>();
}

void JsonFields::get(const char* key, bool& v) const {
  if (!j_.contains(key)) return;
  DOJO_CHECK(j_[key].is_boolean(), what_ + ": field '" + key + "' must be true or false");
  v = j_[key].get<bool>();
}

void check_positive(const std::string& what, const char* field, int64_t value) {
  DOJO_CHECK(value > 0, what + ": field '" + field + "' must be positive, got " + std::to_string(value));
}

nlohmann::json finite_or_null(double value) {
  return std::isfinite(value) ? nlohmann::json(value) : nlohmann::json(nullptr);
}

}  // namespace dojo
