// Reading JSON files with errors that name the file.
#pragma once

#include <filesystem>

#include <nlohmann/json.hpp>

namespace dojo {

// Parses the JSON document at `path`. Throws dojo::Error "PATH: cannot open: ..." or
// "PATH: invalid JSON: ...".
nlohmann::json read_json_file(const std::filesystem::path& path);

}  // namespace dojo
