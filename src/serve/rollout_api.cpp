#include "serve/rollout_api.h"

#include "data/action_rows.h"

#include <array>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "core/error.h"
#include "io/jpeg.h"
#include "io/video.h"
#include "serve/model_host.h"

namespace dojo::serve {

namespace {

constexpr char kAlphabet[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

HttpReply bad_request(const std::string& message) {
  return {400, "application/json", nlohmann::json{{"error", message}}.dump()};
}

}  // namespace

// Written here because Boost's base64 is an internal detail (boost::beast::detail) and the codec
// is a few lines; tested against RFC 4648's vectors.
std::string base64_encode(std::string_view bytes) {
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  for (size_t i = 0; i < bytes.size(); i += 3) {
    const size_t n = std::min<size_t>(3, bytes.size() - i);
    uint32_t v = 0;
    for (size_t j = 0; j < 3; ++j) v = (v << 8) | (j < n ? static_cast<uint8_t>(bytes[i + j]) : 0);
    for (size_t j = 0; j < 4; ++j) out += j <= n ? kAlphabet[(v >> (18 - 6 * j)) & 63] : '=';
  }
  return out;
}

std::string base64_decode(std::string_view text, const std::string& what) {
  std::array<int, 256> value;
  value.fill(-1);
  for (int i = 0; i < 64; ++i) value[static_cast<uint8_t>(kAlphabet[i])] = i;
  DOJO_CHECK(text.size() % 4 == 0, what + ": base64 length must be a multiple of 4");
  std::string out;
  out.reserve(text.size() / 4 * 3);
  for (size_t i = 0; i < text.size(); i += 4) {
    uint32_t v = 0;
    int pad = 0;
    for (size_t j = 0; j < 4; ++j) {
      const char c = text[i + j];
      if (c == '=' && i + 4 == text.size() && j >= 2) {
        ++pad;
        v <<= 6;
        continue;
      }
      DOJO_CHECK(pad == 0 && value[static_cast<uint8_t>(c)] >= 0, what + ": not valid base64");
      v = (v << 6) | static_cast<uint32_t>(value[static_cast<uint8_t>(c)]);
    }
    out += static_cast<char>((v >> 16) & 255);
    if (pad < 2) out += static_cast<char>((v >> 8) & 255);
    if (pad < 1) out += static_cast<char>(v & 255);
  }
  return out;
}

HttpReply run_rollout_request(const ModelHost& host, const std::string& body, ServerMetrics& metrics,
                              const RolloutLimits& limits) {
  const auto start_time = std::chrono::steady_clock::now();
  try {
    const auto request = nlohmann::json::parse(body, nullptr, /*allow_exceptions=*/false);
    DOJO_CHECK(!request.is_discarded() && request.is_object(), "request body must be a JSON object");
    const auto string_field = [&](const char* name) {
      DOJO_CHECK(!request.contains(name) || request[name].is_string(),
                 std::string("'") + name + "' must be a string");
      return request.value(name, std::string());
    };
    const auto model = string_field("model");
    const auto format = request.contains("format") ? string_field("format") : std::string("mp4");
    DOJO_CHECK(format == "mp4" || format == "jpeg", "'format' must be \"mp4\" or \"jpeg\"");
    DOJO_CHECK(!request.contains("seed") || request["seed"].is_number_unsigned(),
               "'seed' must be a non-negative integer");
    DOJO_CHECK(request.contains("actions"), "missing 'actions'");
    const auto rows = data::action_rows_from_json(request["actions"], "'actions'");  // [n, w]
    // One frame per action row after the start frame: refused before any model runs.
    if (rows.size(0) + 1 > limits.max_frames) {
      metrics.error();
      return {413, "application/json",
              nlohmann::json{{"error", "'actions': " + std::to_string(rows.size(0)) + " rows ask for " +
                                           std::to_string(rows.size(0) + 1) +
                                           " frames; this server makes at most " +
                                           std::to_string(limits.max_frames) +
                                           " per request (dojo serve --max-rollout-frames)"}}
                  .dump()};
    }

    auto generator = host.make_generator(model);
    const int64_t per_step = generator->actions_per_step();
    DOJO_CHECK(rows.size(0) % per_step == 0, "'actions': this model takes " + std::to_string(per_step) +
                                                 " actions per step; got " + std::to_string(rows.size(0)) +
                                                 " (not a multiple)");
    StartFrame start;
    if (request.contains("image")) {
      DOJO_CHECK(request["image"].is_string(), "'image' must be a base64 JPEG string");
      start.frame = host.fit_image(
          model, io::decode_jpeg(base64_decode(request["image"].get<std::string>(), "'image'"), "'image'"));
    } else {
      start = host.start_frame(model, string_field("episode"));
    }
    torch::Tensor layout = rows;
    if (rows.size(1) != data::kUnifiedActionDim) {
      auto chunker = host.chunker(model);
      DOJO_CHECK(
          chunker && rows.size(1) == chunker->width(),
          "'actions': rows must have 384 values" +
              (chunker ? " or " + std::to_string(chunker->width()) + " (raw commands)" : std::string()));
      torch::Tensor baseline = start.baseline;
      if (request.contains("baseline"))
        baseline = data::action_rows_from_json(nlohmann::json::array({request["baseline"]}), "'baseline'")[0];
      if (baseline.defined()) {
        DOJO_CHECK(baseline.size(0) == chunker->width(),
                   "'baseline' must have " + std::to_string(chunker->width()) + " values");
        chunker->set_baseline(baseline);
      }
      std::vector<torch::Tensor> chunks;
      for (int64_t i = 0; i < rows.size(0); i += per_step)
        chunks.push_back(chunker->push(rows.narrow(0, i, per_step)));
      layout = torch::cat(chunks);  // [n, 384]
    }

    std::vector<torch::Tensor> frames = {generator->reset(start.frame, request.value("seed", uint64_t{0}))};
    for (int64_t i = 0; i < layout.size(0); i += per_step) {
      const double spent =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - start_time).count();
      if (limits.stopping != nullptr && limits.stopping->load()) {
        metrics.error();
        return {503, "application/json",
                nlohmann::json{{"error", "the server is stopping (after " +
                                             std::to_string(frames.size() - 1) + " steps of the rollout)"}}
                    .dump()};
      }
      if (spent > limits.max_seconds) {
        metrics.error();
        return {
            503, "application/json",
            nlohmann::json{{"error", "the rollout ran past " +
                                         std::to_string(static_cast<int64_t>(limits.max_seconds)) +
                                         " s after " + std::to_string(frames.size() - 1) +
                                         " steps (dojo serve --max-rollout-seconds); ask for fewer frames"}}
                .dump()};
      }
      frames.push_back(generator->step(layout.narrow(0, i, per_step)));  // [n, H, W, 3]
      metrics.observe_step(generator->last_step_seconds());
      metrics.frames_generated(frames.back().size(0));
    }
    const auto video = torch::cat(frames);  // [1 + N, H, W, 3]
    if (format == "jpeg") {
      nlohmann::json out = {{"frames", nlohmann::json::array()}, {"episode", start.episode}};
      for (int64_t i = 0; i < video.size(0); ++i)
        out["frames"].push_back(base64_encode(io::encode_jpeg(video[i], limits.jpeg_quality)));
      return {200, "application/json", out.dump()};
    }
    // The encoder writes files; a private temporary one is read back and removed.
    const auto tmp =
        std::filesystem::temp_directory_path() /
        ("dojo-rollout-" + std::to_string(std::chrono::steady_clock::now().time_since_epoch().count()) + "-" +
         std::to_string(reinterpret_cast<uintptr_t>(&frames)) + ".mp4");
    io::VideoWriterOptions w;
    w.fps = 10;
    io::write_video(tmp.string(), video, w);
    std::ifstream in(tmp, std::ios::binary);
    std::ostringstream bytes;
    bytes << in.rdbuf();
    in.close();
    std::filesystem::remove(tmp);
    return {200, "video/mp4", bytes.str()};
  } catch (const std::exception& e) {
    metrics.error();
    return bad_request(e.what());
  }
}

}  // namespace dojo::serve
