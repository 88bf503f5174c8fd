#include "data/action_rows.h"

#include <torch/torch.h>

#include <cmath>
#include <nlohmann/json.hpp>
#include <vector>

#include "core/error.h"

namespace dojo::data {

at::Tensor action_rows_from_json(const nlohmann::json& rows, const std::string& where, size_t max_rows) {
  DOJO_CHECK(rows.is_array() && !rows.empty() && (max_rows == 0 || rows.size() <= max_rows),
             where + " must be a non-empty array of rows" +
                 (max_rows ? " (at most " + std::to_string(max_rows) + ")" : std::string()));
  const size_t width = rows[0].is_array() ? rows[0].size() : 0;
  DOJO_CHECK(width > 0 && width <= 1024, where + ": every row must be an array of numbers");
  std::vector<float> values;
  values.reserve(rows.size() * width);
  for (const auto& row : rows) {
    DOJO_CHECK(row.is_array() && row.size() == width,
               where + ": every row must have " + std::to_string(width) + " values");
    for (const auto& x : row) {
      DOJO_CHECK(x.is_number() && std::isfinite(x.get<double>()), where + ": values must be finite numbers");
      values.push_back(x.get<float>());
    }
  }
  return torch::tensor(values).view({static_cast<int64_t>(rows.size()), static_cast<int64_t>(width)});
}

}  // namespace dojo::data
