// Reading JSON files and config objects with errors that name the file or the field.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>

#include <nlohmann/json.hpp>

namespace dojo {

// Parses the JSON document at `path`. Throws dojo::Error "PATH: cannot open: ..." or
// "PATH: invalid JSON: ...".
nlohmann::json read_json_file(const std::filesystem::path& path);

// Optional typed fields of a JSON object, for config parsers: an absent field leaves the value as
// it was; a present one of the wrong type throws dojo::Error "WHAT: field 'KEY' must be ...".
class JsonFields {
 public:
  // Throws dojo::Error "WHAT: expected a JSON object" unless `j` is one.
  JsonFields(const nlohmann::json& j, std::string what);
  void get(const char* key, int64_t& v) const;
  void get(const char* key, double& v) const;
  void get(const char* key, bool& v) const;

 private:
  const nlohmann::json& j_;
  std::string what_;
};

// A number for a JSON document: the value when finite, else null (JSON has no NaN or infinity, and
// a metric that could not be measured must read as missing, not as a number).
nlohmann::json finite_or_null(double value);

// Throws dojo::Error "WHAT: field 'FIELD' must be positive, got V" unless value > 0.
void check_positive(const std::string& what, const char* field, int64_t value);

}  // namespace dojo
