#include "models/value_model.h"

#include <torch/torch.h>

#include <algorithm>
#include <numeric>

#include "core/checkpoint.h"
#include "core/error.h"
#include "core/state_dict.h"

namespace dojo::models {

ValueModel make_value_model(int64_t horizon) {
  DOJO_CHECK(horizon > 0, "value model: the horizon must be positive");
  SuccessDetectorConfig config;
  config.window = 4;
  config.stride = 1;
  ValueModel model;
  model.network = SuccessDetector(config);
  model.horizon = horizon;
  return model;
}

std::vector<double> window_values(ValueModel& model, const torch::Tensor& video_u8) {
  const int64_t w = model.window();
  DOJO_CHECK(video_u8.dim() == 4 && video_u8.size(0) >= w,
             "value model: a video of at least " + std::to_string(w) + " frames [T, H, W, 3] is needed");
  const auto windows = video_u8.unfold(0, w, 1).permute({0, 4, 1, 2, 3});  // [T - w + 1, w, H, W, 3]
  const auto values = success_probability(model.network, windows.contiguous()).to(torch::kFloat64);
  return std::vector<double>(values.data_ptr<double>(), values.data_ptr<double>() + values.numel());
}

double video_value(const std::vector<double>& values, double rise) {
  DOJO_CHECK(!values.empty(), "video value: no window values");
  double lowest = values.front();
  size_t end = values.size();
  for (size_t i = 1; i < values.size(); ++i) {
    if (values[i] > lowest + rise) {  // a boundary passed: the next subtask's values start high
      end = i;
      break;
    }
    lowest = std::min(lowest, values[i]);
  }
  return std::accumulate(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(end), 0.0) /
         static_cast<double>(end);
}

CheckpointData value_model_checkpoint(const ValueModel& model) {
  CheckpointData data;
  auto config = model.network->config().to_json();
  config["horizon"] = model.horizon;
  data.config = {{"model", "value_model"}, {"config", config}};
  for (const auto& [name, t] : state_dict(*model.network)) data.model.emplace_back("value." + name, t);
  return data;
}

ValueModel load_value_model(const std::filesystem::path& dir) {
  const auto ckpt = Checkpoint::open(resolve_checkpoint_dir(dir));
  const auto& cfg = ckpt.config();
  const auto file = (ckpt.dir() / "config.json").string();
  DOJO_CHECK(cfg.contains("model") && cfg["model"] == "value_model" && cfg.contains("config"),
             file + ": not a value model checkpoint (model != value_model)");
  ValueModel model;
  try {
    auto backbone = cfg["config"];
    DOJO_CHECK(backbone.is_object() && backbone.contains("horizon") &&
                   backbone["horizon"].is_number_integer() && backbone["horizon"].get<int64_t>() > 0,
               "field 'horizon' must be a positive integer");
    model.horizon = backbone["horizon"].get<int64_t>();
    backbone.erase("horizon");
    model.network = SuccessDetector(SuccessDetectorConfig::from_json(backbone));
    DOJO_CHECK(model.network->config().stride == 1,
               "field 'stride' must be 1 (values are read from consecutive frames)");
  } catch (const Error& e) {
    throw Error(file + ": " + e.what());
  }
  LoadOptions opts;
  opts.prefix = "value.";
  load_state_dict(*model.network, ckpt.model(), opts);
  model.network->eval();
  return model;
}

}  // namespace dojo::models
