// Action rows sent as JSON (`dojo wm stream`'s input lines, a served session's step messages,
// `POST /v1/rollout`): one parser, so every entry point accepts and refuses the same things.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstddef>
#include <nlohmann/json_fwd.hpp>
#include <string>

namespace dojo::data {

// A non-empty JSON array of rows, each an array of the same number (1-1024) of finite numbers,
// -> [n, w] float32. `max_rows` > 0 caps n. Throws dojo::Error starting with `where`: "... must be
// a non-empty array of rows", "... every row must have W values", "... values must be finite numbers".
at::Tensor action_rows_from_json(const nlohmann::json& rows, const std::string& where, size_t max_rows = 0);

}  // namespace dojo::data
