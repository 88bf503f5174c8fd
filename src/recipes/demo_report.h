// The demo's self-contained HTML report, written from the stage records alone (OUT/stages/*.json
// and the files the stages left), so a finished demo re-writes it without running anything.
#pragma once

#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>

namespace dojo::recipes {

// Writes OUT/report.html and OUT/eval.md; returns the markdown of eval.md.
std::string write_demo_report(const std::filesystem::path& out, const nlohmann::json& stages);

}  // namespace dojo::recipes
