#include "models/dit.h"

#include <torch/torch.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <tuple>

#include "core/safetensors.h"
#include "core/state_dict.h"
#include "test_util.h"

namespace dojo::models {

namespace {

// A missing fixture fails the test that asks for it, naming the file: golden tests never skip
// (tests/golden/README.md).
std::optional<SafetensorsFile> open_fixture(const std::string& name) {
  const auto path = test::golden_dir() / name;
  if (!std::filesystem::exists(path)) {
    ADD_FAILURE() << path << " is missing: golden fixtures are never skipped (tests/golden/README.md)";
    return std::nullopt;
  }
  return SafetensorsFile::open(path);
}

// name, shape, dtype rows of a keys/*.tsv file (none, and a failure naming it, when it is missing).
std::vector<DitTensorSpec> read_key_list(const std::string& name) {
  std::vector<DitTensorSpec> out;
  const auto path = test::golden_dir() / "keys" / name;
  if (!std::filesystem::exists(path)) {
    ADD_FAILURE() << path << " is missing: golden fixtures are never skipped (tests/golden/README.md)";
    return out;
  }
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream row(line);
    std::string key, shape, dtype;
    std::getline(row, key, '\t');
    std::getline(row, shape, '\t');
    std::getline(row, dtype, '\t');
    DitTensorSpec s;
    s.name = key;
    for (char& ch : shape)
      if (ch == '[' || ch == ']' || ch == ',') ch = ' ';
    std::istringstream dims(shape);
    int64_t v;
    while (dims >> v) s.shape.push_back(v);
    s.dtype = dtype == "int64" ? torch::kInt64 : torch::kFloat32;
    out.push_back(s);
  }
  return out;
}

void expect_specs_equal(const std::vector<DitTensorSpec>& ours, const std::vector<DitTensorSpec>& ref,
                        const std::string& prefix) {
  ASSERT_EQ(ours.size(), ref.size());
  for (size_t i = 0; i < ours.size(); ++i) {
    EXPECT_EQ(prefix + ours[i].name, ref[i].name) << "entry " << i;
    EXPECT_EQ(ours[i].shape, ref[i].shape) << ref[i].name;
    EXPECT_EQ(ours[i].dtype, ref[i].dtype) << ref[i].name;
  }
}

// Random non-zero weights everywhere (the default init zeroes the action fc2), seeded.
void randomize(ActionDitImpl& net, uint64_t seed) {
  torch::manual_seed(seed);
  torch::NoGradGuard no_grad;
  // As the golden fixture: weights N(0,1)/sqrt(fan_in), norm weights 1 + 0.2 N, biases 0.1 N.
  for (auto& item : net.named_parameters()) {
    const std::string& name = item.key();
    auto& p = item.value();
    const bool norm = name.size() > 11 && name.compare(name.size() - 11, 11, "norm.weight") == 0;
    if (norm)
      p.copy_(1 + 0.2 * torch::randn_like(p));
    else if (p.dim() == 1)
      p.copy_(0.1 * torch::randn_like(p));
    else
      p.copy_(torch::randn_like(p) / std::sqrt(static_cast<double>(p.size(1))));
  }
}

// Default init, with the action fc2 layers re-drawn (they start at zero) so actions matter.
void default_init_with_actions(ActionDitImpl& net, uint64_t seed) {
  torch::manual_seed(seed);
  net.action_embedder_B_D->fc2->reset_parameters();
  net.action_embedder_B_3D->fc2->reset_parameters();
}

DitInputs random_inputs(const DitConfig& c, int64_t B, int64_t T, int64_t H, int64_t W, uint64_t seed) {
  torch::manual_seed(seed);
  DitInputs in;
  in.x = torch::randn({B, c.in_channels, T, H, W});
  in.timesteps = torch::rand({B, T}) * 1000;
  in.condition_mask = torch::zeros({B, 1, T, H, W});
  in.condition_mask.slice(2, 0, 1).fill_(1);
  in.actions = torch::randn({B, c.actions_per_latent_frame * (T - 1), c.action_dim});
  in.context = torch::randn({B, 3, c.crossattn_emb_channels});
  return in;
}

// Frame t of `in` alone, for frame-by-frame calls through `cache` (k actions per latent frame).
DitInputs frame_step(const DitInputs& in, int64_t t, int64_t k, std::vector<DitKvCache>& cache) {
  DitInputs step;
  step.x = in.x.slice(2, t, t + 1);
  step.timesteps = in.timesteps.slice(1, t, t + 1);
  step.condition_mask = in.condition_mask.slice(2, t, t + 1);
  step.context = in.context;
  step.frame_offset = t;
  step.actions = t == 0 ? torch::Tensor() : in.actions.slice(1, (t - 1) * k, t * k);
  step.kv_cache = &cache;
  return step;
}

}  // namespace

// --- RoPE and timestep embedding (dit_rope_temb) ----------------------------------------------

TEST(DitRope, TablesMatchGolden) {
  auto g = open_fixture("dit_rope_temb.safetensors");
  ASSERT_TRUE(g) << "golden fixture missing from " << test::golden_dir();
  EXPECT_LE(test::max_abs(rope_dim_range(42, false), g->tensor("rope128_dim_spatial_range")), 0.0);
  EXPECT_LE(test::max_abs(rope_dim_range(44, false), g->tensor("rope128_dim_temporal_range")), 0.0);
  const auto axes = rope_axis_dims(128);
  EXPECT_EQ(axes.t, 44);
  EXPECT_EQ(axes.h, 42);
  EXPECT_EQ(axes.w, 42);

  const auto a128 = rope_angles_3d(128, 3, 4, 5);
  const auto a32 = rope_angles_3d(32, 4, 4, 6);
  // Full 480x640 video table (4 x 30 x 40 tokens) at the fixture's token indices.
  const auto full = rope_angles_3d(128, 4, 30, 40);
  ASSERT_EQ(full.size(0), 4800);
  const auto idx = g->tensor("rope128_480x640_token_index");
  const std::vector<std::tuple<std::string, torch::Tensor, double>> checks = {
      {"rope128_angles", a128, 1e-5},
      {"rope128_cos", a128.cos(), 2e-6},
      {"rope128_sin", a128.sin(), 2e-6},
      {"rope128_q_rotated", apply_rope(g->tensor("rope128_q_in"), a128), 2e-6},
      {"rope32_angles", a32, 1e-5},
      {"rope32_cos", a32.cos(), 2e-6},
      {"rope32_sin", a32.sin(), 2e-6},
      {"rope128_480x640_angles_at_index", full.index_select(0, idx), 1e-5}};
  std::string report = "rope max abs:";
  for (const auto& [name, ours, tol] : checks) {
    const double err = test::max_abs(ours, g->tensor(name));
    EXPECT_LE(err, tol) << name;
    char buf[96];
    std::snprintf(buf, sizeof(buf), " %s %.2g", name.c_str(), err);
    report += buf;
  }
  std::printf("%s\n", report.c_str());
}

TEST(DitRope, FrameOffsetIsAbsolutePosition) {
  const auto full = rope_angles_3d(64, 6, 3, 4);
  const auto tail = rope_angles_3d(64, 2, 3, 4, /*frame_offset=*/4);
  EXPECT_EQ(test::max_abs(tail, full.slice(0, 4 * 12)), 0.0);
  // bf16-rounded exponents differ from the exact ones, and only in the frequencies.
  const auto rounded = rope_angles_3d(128, 2, 3, 4, 0, 3.0, 3.0, 1.0, /*bf16_ranges=*/true);
  EXPECT_GT(test::max_abs(rounded, rope_angles_3d(128, 2, 3, 4)), 1e-4);
  EXPECT_NEAR(rope_dim_range(42, true)[1].item<double>(), 0.047607, 1e-6);
}

TEST(DitRope, ApplyRopeIsRotateHalf) {
  // Element i pairs with i + d/2 and both use angle a[i]: a norm-preserving 2-D rotation.
  torch::manual_seed(4);
  const auto x = torch::randn({2, 12, 3, 32});
  const auto angles = rope_angles_3d(32, 1, 3, 4);
  const auto y = apply_rope(x, angles);
  const auto pair_norm = [](const torch::Tensor& t) {
    return t.slice(-1, 0, 16).pow(2) + t.slice(-1, 16).pow(2);
  };
  EXPECT_LE(test::max_abs(pair_norm(y), pair_norm(x)), 1e-4);
  const auto a = angles.flatten(1, 2);  // [12, 1, 32]
  const auto expect_lo =
      x.slice(-1, 0, 16) * a.slice(-1, 0, 16).cos() - x.slice(-1, 16) * a.slice(-1, 0, 16).sin();
  EXPECT_LE(test::max_abs(y.slice(-1, 0, 16), expect_lo), 1e-5);
}

TEST(DitTimestep, SinusoidMatchesGolden) {
  auto g = open_fixture("dit_rope_temb.safetensors");
  ASSERT_TRUE(g) << "golden fixture missing from " << test::golden_dir();
  const auto raw = g->tensor("temb_timesteps_raw");
  const auto scaled = raw * 0.001;
  EXPECT_EQ(test::max_abs(scaled, g->tensor("temb_timesteps_scaled")), 0.0);
  for (int64_t dim : {2048, 64, 80}) {
    const double err = test::max_abs(timestep_sinusoid(scaled, dim), g->tensor("temb" + std::to_string(dim)));
    EXPECT_LE(err, 2e-6) << dim;
    std::printf("temb%ld max abs %.2g\n", static_cast<long>(dim), err);
  }
  // Cosine half first: t = 0 gives [1..1, 0..0].
  const auto zero = timestep_sinusoid(torch::zeros({1}), 8);
  EXPECT_EQ(test::max_abs(zero, torch::tensor({{1.f, 1.f, 1.f, 1.f, 0.f, 0.f, 0.f, 0.f}})), 0.0);
}

// --- config and parameter inventory -----------------------------------------------------------

TEST(DitConfig, GoldenTinyMatchesFixtureKwargs) {
  auto g = open_fixture("dit_tiny_weights.safetensors");
  ASSERT_TRUE(g) << "golden fixture missing from " << test::golden_dir();
  const auto kwargs = nlohmann::json::parse(g->metadata().at("config"));
  EXPECT_EQ(DitConfig::from_reference_kwargs(kwargs).to_json(), DitConfig::golden_tiny().to_json());
}

TEST(DitConfig, JsonRoundTripAndErrors) {
  for (const auto& c : {DitConfig::small(), DitConfig::released_14b(), DitConfig::student_2b()})
    EXPECT_EQ(DitConfig::from_json(c.to_json()).to_json(), c.to_json());
  auto bad = DitConfig::small().to_json();
  bad["num_heads"] = 3;
  EXPECT_NE(test::error_message([&] { DitConfig::from_json(bad); }).find("num_heads"), std::string::npos);
  bad = DitConfig::small().to_json();
  bad["model_channels"] = "wide";
  EXPECT_NE(test::error_message([&] { DitConfig::from_json(bad); }).find("model_channels"),
            std::string::npos);
  bad = DitConfig::small().to_json();
  bad["rope_bf16_ranges"] = 1;
  EXPECT_NE(test::error_message([&] { DitConfig::from_json(bad); }).find("rope_bf16_ranges"),
            std::string::npos);
  bad = DitConfig::small().to_json();
  bad["patch_temporal"] = 2;
  EXPECT_NE(test::error_message([&] { DitConfig::from_json(bad); }).find("patch_temporal"),
            std::string::npos);
  EXPECT_EQ(DitConfig::student_2b().rope_seq_len(), 256);
  EXPECT_EQ(DitConfig::released_2b().rope_seq_len(), 128);
}

TEST(DitConfig, FromWeightsReadsTheArchitecture) {
  auto g = open_fixture("dit_tiny_weights.safetensors");
  ASSERT_TRUE(g) << "golden fixture missing from " << test::golden_dir();
  EXPECT_EQ(DitConfig::from_weights(*g).to_json(), DitConfig::golden_tiny().to_json());

  // A saved small model (no projection, custom action width) round-trips and loads strictly.
  auto c = DitConfig::small();
  c.num_blocks = 2;
  c.use_crossattn_projection = false;
  c.action_dim = 12;
  c.action_hidden_dim = 40;
  c.max_frames = 256;
  c.zero_init_action_fc2 = false;
  ActionDit net(c);
  NamedTensors named;
  for (const auto& [name, t] : state_dict(*net)) named.emplace_back("net." + name, t);
  test::TempDir dir;
  save_safetensors(dir / "dit.safetensors", named);
  const auto file = SafetensorsFile::open(dir / "dit.safetensors");
  const auto back = DitConfig::from_weights(file);
  EXPECT_EQ(back.to_json(), c.to_json());
  ActionDit loaded(back);
  LoadOptions opts;
  opts.prefix = "net.";
  EXPECT_TRUE(load_state_dict(*loaded, file, opts).ok());

  NamedTensors partial(named.begin(), named.begin() + 4);
  save_safetensors(dir / "partial.safetensors", partial);
  EXPECT_NE(test::error_message([&] {
              DitConfig::from_weights(SafetensorsFile::open(dir / "partial.safetensors"));
            }).find("net.x_embedder.proj.1.weight"),
            std::string::npos);
}

TEST(DitKeys, Released2BKeyListShapesAndCount) {
  const auto ref = read_key_list("dit_2B_action384_keys.tsv");
  ASSERT_FALSE(ref.empty()) << "key list missing from " << test::golden_dir() / "keys";
  ASSERT_EQ(ref.size(), 584u);
  const auto ours = dit_parameter_shapes(DitConfig::released_2b());
  expect_specs_equal(ours, ref, "net.");
  int64_t total = 0;
  for (const auto& s : ref) {
    int64_t n = 1;
    for (int64_t v : s.shape) n *= v;
    total += n;
  }
  EXPECT_EQ(total, 2151474351);  // keys/README.md (buffers included)
  const int64_t params = dit_parameter_count(DitConfig::released_2b());
  EXPECT_EQ(params, 2151474351 - 175);  // minus accum_* (4) and the RoPE buffers (128 + 21 + 22)
  EXPECT_NEAR(params / 1e9, 2.151, 0.0005);
  // The student differs only in the RoPE seq buffer.
  const auto student = dit_parameter_shapes(DitConfig::student_2b());
  EXPECT_EQ(student[5].name, "pos_embedder.seq");
  EXPECT_EQ(student[5].shape, std::vector<int64_t>{256});
}

TEST(DitKeys, Released14BShapeArithmetic) {
  const auto ref = read_key_list("dit_14B_action384_keys.tsv");
  ASSERT_FALSE(ref.empty()) << "key list missing from " << test::golden_dir() / "keys";
  ASSERT_EQ(ref.size(), 744u);
  expect_specs_equal(dit_parameter_shapes(DitConfig::released_14b()), ref, "net.");
  EXPECT_EQ(dit_parameter_count(DitConfig::released_14b()), 14850453679 - 175);
}

TEST(DitKeys, ModuleStateDictEqualsShapeInventory) {
  // The module built from a config registers exactly what dit_parameter_shapes lists, so the
  // 2B/14B checks above hold for the module too.
  auto no_proj = DitConfig::golden_tiny();
  no_proj.use_crossattn_projection = false;
  no_proj.action_hidden_dim = 24;
  for (const auto& c : {DitConfig::golden_tiny(), DitConfig::small(), no_proj}) {
    ActionDit net(c);
    const auto sd = state_dict(*net);
    const auto specs = dit_parameter_shapes(c);
    ASSERT_EQ(sd.size(), specs.size());
    for (size_t i = 0; i < sd.size(); ++i) {
      EXPECT_EQ(sd[i].first, specs[i].name);
      EXPECT_EQ(sd[i].second.sizes().vec(), specs[i].shape) << specs[i].name;
      EXPECT_EQ(sd[i].second.scalar_type(), specs[i].dtype) << specs[i].name;
    }
    EXPECT_EQ(net->num_parameters(), dit_parameter_count(c));
  }
}

// --- golden network parity (dit_tiny) -----------------------------------------------------------

namespace {
struct TinyGolden {
  SafetensorsFile weights, io;
};

std::optional<TinyGolden> open_tiny() {
  auto w = open_fixture("dit_tiny_weights.safetensors");
  auto io = open_fixture("dit_tiny_io.safetensors");
  if (!w || !io) return std::nullopt;
  return TinyGolden{std::move(*w), std::move(*io)};
}

ActionDit tiny_model(const TinyGolden& g) {
  ActionDit net(DitConfig::from_reference_kwargs(nlohmann::json::parse(g.weights.metadata().at("config"))));
  LoadOptions opts;
  opts.prefix = "net.";
  const auto report = load_state_dict(*net, g.weights, opts);
  EXPECT_TRUE(report.ok()) << report.to_string();
  net->eval();
  return net;
}

DitInputs tiny_inputs(const TinyGolden& g, const std::string& case_name) {
  DitInputs in;
  in.x = g.io.tensor("x_t");
  in.timesteps = g.io.tensor(case_name + "_timesteps");
  in.condition_mask = g.io.tensor("condition_mask");
  in.padding_mask = g.io.tensor("padding_mask");
  in.actions = g.io.tensor("action");
  in.context = g.io.tensor("crossattn_emb");
  return in;
}
}  // namespace

TEST(DitGolden, TinyForwardAndIntermediates) {
  test::OneThread one_thread;
  auto g = open_tiny();
  ASSERT_TRUE(g) << "golden fixture missing from " << test::golden_dir();
  auto net = tiny_model(*g);
  torch::NoGradGuard no_grad;
  for (const std::string name : {"tshared", "tframe"}) {
    const auto out = net->forward_with_intermediates(tiny_inputs(*g, name));
    const auto& io = g->io;
    // (our name, fixture name, tolerance from dit_tiny.md)
    const std::vector<std::tuple<std::string, std::string, double>> checks = {
        {"x_embedded", "x_embedded", 1e-5},
        {"rope_emb", "rope_emb", 1e-5},
        {"crossattn_proj_out", "crossattn_proj_out", 1e-5},
        {"action_emb_B_D", "action_emb_B_D", 1e-5},
        {"action_emb_B_3D", "action_emb_B_3D", 1e-5},
        {"t_emb_raw", name + "_t_emb_raw", 1e-5},
        {"adaln_lora_raw", name + "_adaln_lora_raw", 1e-5},
        {"t_emb_normed", name + "_t_emb_normed", 1e-5},
        {"block0_out", name + "_block0_out", 1e-4},
        {"block1_out", name + "_block1_out", 1e-4},
        {"final_layer_out", name + "_final_layer_out", 1e-4},
        {"velocity", name + "_velocity", 1e-4}};
    std::string report = name + " max abs:";
    for (const auto& [ours, theirs, tol] : checks) {
      const double err = test::max_abs(out.at(ours), io.tensor(theirs));
      EXPECT_LE(err, tol) << theirs;
      char buf[96];
      std::snprintf(buf, sizeof(buf), " %s %.2g", ours.c_str(), err);
      report += buf;
    }
    std::printf("%s\n", report.c_str());
    // forward() is the same computation without the captures.
    EXPECT_EQ(test::max_abs(net->forward(tiny_inputs(*g, name)), out.at("velocity")), 0.0) << name;
    // A context projected once up front gives the same result.
    auto pre = tiny_inputs(*g, name);
    pre.projected_context = net->project_context(pre.context);
    pre.context = torch::Tensor();
    EXPECT_EQ(test::max_abs(net->forward(pre), out.at("velocity")), 0.0) << name;
  }
}

TEST(DitGolden, TinyActionsMatter) {
  // The fixture's weights make the action path significant: dropping the actions must move the
  // output by far more than the tolerance (guards against a silently ignored action input).
  auto g = open_tiny();
  ASSERT_TRUE(g) << "golden fixture missing from " << test::golden_dir();
  auto net = tiny_model(*g);
  torch::NoGradGuard no_grad;
  auto in = tiny_inputs(*g, "tshared");
  in.actions = torch::Tensor();
  EXPECT_GT(test::max_abs(net->forward(in), g->io.tensor("tshared_velocity")), 0.1);
}

TEST(DitGolden, TinyDenoiseVelocity) {
  auto g = open_tiny();
  ASSERT_TRUE(g) << "golden fixture missing from " << test::golden_dir();
  auto net = tiny_model(*g);
  torch::NoGradGuard no_grad;
  const auto base = tiny_inputs(*g, "tshared");
  const auto gt = g->io.tensor("denoise_gt_x0"), noise = g->io.tensor("denoise_noise");
  const auto v = denoise_velocity(*net, base, g->io.tensor("x_t"), gt, noise, g->io.tensor("condition_mask"));
  const double err = test::max_abs(v, g->io.tensor("denoise_velocity"));
  EXPECT_LE(err, 1e-4);
  std::printf("denoise_velocity max abs %.2g\n", err);
  // Conditioning frame 0 carries exactly noise - gt.
  EXPECT_EQ(test::max_abs(v.select(2, 0), (noise - gt).select(2, 0)), 0.0);
}

// --- behaviour on the small config --------------------------------------------------------------

TEST(DitSmall, WholeClipActionInjectionAblation) {
  test::OneThread one_thread;
  auto c = DitConfig::small();
  c.model_channels = 64;
  c.num_heads = 2;
  c.num_blocks = 1;
  c.whole_clip_actions = 12;
  c.zero_init_action_fc2 = false;
  ActionDit net(c);
  EXPECT_EQ(net->action_embedder_B_D->fc1->weight.size(1), 12 * 384);
  net->eval();
  torch::NoGradGuard no_grad;
  auto in = random_inputs(c, 1, 4, 4, 4, 3);
  in.timesteps = torch::full({1, 1}, 500.0);
  in.actions = torch::randn({1, 12, 384});
  const auto a = net->forward_with_intermediates(in);
  // One embedding for the whole clip: a single modulation row shared by all four frames, and it
  // depends on the last action too.
  EXPECT_EQ(a.at("t_emb_normed").sizes(), (std::vector<int64_t>{1, 1, 64}));
  in.actions[0][11][0] += 1.0;
  EXPECT_GT(test::max_abs(net->forward_with_intermediates(in).at("t_emb_normed"), a.at("t_emb_normed")),
            1e-6);
  in.actions = torch::randn({1, 8, 384});
  EXPECT_THROW(net->forward(in), std::exception);
  EXPECT_EQ(DitConfig::from_json(c.to_json()).whole_clip_actions, 12);
}

TEST(DitFlops, CountsTokenLinearsAndAttention) {
  // 2B at 480x640, 13 frames: 4 x 30 x 40 = 4800 tokens. Per token and block the linear maps
  // hold 4 D^2 (self-attn) + 2 D^2 (cross q, o) + 8 D^2 (MLP) weights; attention adds 2 L D for
  // scores and values. Everything else (context, modulation, embeddings) is a few percent.
  const auto c = DitConfig::released_2b();
  const double D = 2048, L = 4800;
  const double blocks = 2 * 28 * (L * 14 * D * D + 2 * L * L * D);
  const double flops = dit_forward_flops(c, 4, 60, 80, 512);
  EXPECT_GT(flops, blocks);
  EXPECT_LT(flops, 1.1 * blocks);
  // Linear in the batch-free sizes it should be: twice the frames, a bit over twice the work.
  EXPECT_GT(dit_forward_flops(c, 8, 60, 80, 512), 2 * flops * 0.99);
}

TEST(DitSmall, BatchIndependence) {
  test::OneThread one_thread;
  const auto c = DitConfig::small();
  ActionDit net(c);
  default_init_with_actions(*net, 11);
  net->eval();
  torch::NoGradGuard no_grad;
  const auto in = random_inputs(c, 3, 3, 8, 8, 12);
  const auto all = net->forward(in);
  for (int64_t b = 0; b < 3; ++b) {
    DitInputs one = in;
    one.x = in.x.slice(0, b, b + 1);
    one.timesteps = in.timesteps.slice(0, b, b + 1);
    one.condition_mask = in.condition_mask.slice(0, b, b + 1);
    one.actions = in.actions.slice(0, b, b + 1);
    one.context = in.context.slice(0, b, b + 1);
    const double err = test::max_abs(net->forward(one), all.slice(0, b, b + 1));
    EXPECT_LE(err, 1e-5) << "sample " << b;
    std::printf("sample %ld alone vs in batch max abs %.2g\n", static_cast<long>(b), err);
  }
}

TEST(DitSmall, BlockCausalMaskEqualsKvCacheStreaming) {
  test::OneThread one_thread;
  const auto c = DitConfig::small();
  ActionDit net(c);
  default_init_with_actions(*net, 21);
  net->eval();
  torch::NoGradGuard no_grad;
  const int64_t B = 2, T = 4, H = 8, W = 8, S = (H / 2) * (W / 2), k = c.actions_per_latent_frame;
  const auto in = random_inputs(c, B, T, H, W, 22);

  DitInputs full = in;
  full.self_attn_mask = dit_block_causal_mask(T, S);
  const auto v_full = net->forward(full);

  // Without the mask, later frames leak into earlier ones (so the test can fail).
  const auto v_bidir = net->forward(in);
  EXPECT_GT(test::max_abs(v_bidir.select(2, 0), v_full.select(2, 0)), 1e-3);

  std::vector<DitKvCache> cache(c.num_blocks);
  std::vector<torch::Tensor> frames;
  for (int64_t t = 0; t < T; ++t) {
    frames.push_back(net->forward(frame_step(in, t, k, cache)));
    EXPECT_EQ(cache[0].tokens(), (t + 1) * S);
  }
  const double err = test::max_abs(torch::cat(frames, 2), v_full);
  EXPECT_LT(err, 1e-5);
  std::printf("block-causal mask vs KV cache max abs %.2g (output max %.2g)\n", err,
              v_full.abs().max().item<double>());

  // A rolling window: window_frames = 2 in the mask equals keeping 1 cached frame.
  DitInputs windowed = in;
  windowed.self_attn_mask = dit_block_causal_mask(T, S, 0, /*window_frames=*/2);
  const auto v_win = net->forward(windowed);
  for (auto& e : cache) e.clear();
  frames.clear();
  for (int64_t t = 0; t < T; ++t) {
    frames.push_back(net->forward(frame_step(in, t, k, cache)));
    for (auto& e : cache) e.keep_last(S);
  }
  EXPECT_LT(test::max_abs(torch::cat(frames, 2), v_win), 1e-5);
}

// An attention sink in the ring: frame 0 stays in view of every later frame while the window
// rolls over the others (the block-causal mask with a sink), and placing the sink's keys later in
// time equals storing frame 0 at the new position.
TEST(DitSmall, RingSinkKeepsTheFirstFrameAndMovesByRotation) {
  test::OneThread one_thread;
  const auto c = DitConfig::small();
  ActionDit net(c);
  default_init_with_actions(*net, 23);
  net->eval();
  torch::NoGradGuard no_grad;
  const int64_t B = 1, T = 6, H = 8, W = 8, S = (H / 2) * (W / 2), k = c.actions_per_latent_frame;
  const auto in = random_inputs(c, B, T, H, W, 24);
  const auto stream = [&](std::vector<DitKvCache>& cache, int64_t window, int64_t sink) {
    for (auto& e : cache) e.set_ring(window, S, sink);
    std::vector<torch::Tensor> frames;
    for (int64_t t = 0; t < T; ++t) {
      frames.push_back(net->forward(frame_step(in, t, k, cache)));
    }
    return torch::cat(frames, 2);  // [B, 16, T, H, W]
  };
  std::vector<DitKvCache> cache(c.num_blocks);
  const auto with_sink = stream(cache, /*window=*/2, /*sink=*/1);
  DitInputs masked = in;
  masked.self_attn_mask = dit_block_causal_mask(T, S, 0, /*window_frames=*/3, /*sink_frames=*/1);
  EXPECT_LT(test::max_abs(with_sink, net->forward(masked)), 1e-5);
  const auto without = stream(cache, 2, 0);  // frame 0 leaves the window at frame 3
  EXPECT_LT(test::max_abs(with_sink.narrow(2, 0, 3), without.narrow(2, 0, 3)), 1e-6);
  EXPECT_GT(test::max_abs(with_sink.narrow(2, 3, 3), without.narrow(2, 3, 3)), 1e-3);

  const auto store_first = [&](std::vector<DitKvCache>& into, int64_t position) {
    for (auto& e : into) e.set_ring(2, S, 1);
    DitInputs first;
    first.x = in.x.slice(2, 0, 1);
    first.timesteps = in.timesteps.slice(1, 0, 1);
    first.condition_mask = in.condition_mask.slice(2, 0, 1);
    first.context = in.context;
    first.frame_offset = position;  // no actions: the first frame's pass wherever it sits
    first.kv_cache = &into;
    net->forward(first);
  };
  std::vector<DitKvCache> moved(c.num_blocks), stored(c.num_blocks);
  store_first(moved, 0);
  store_first(stored, 3);
  double worst = 0, moved_by = 0;
  for (int64_t b = 0; b < c.num_blocks; ++b) {
    const auto before = moved[b].k.narrow(2, 0, S).clone();
    for (int64_t shift = 1; shift <= 3; ++shift) {  // one frame a step, as a stream moves it
      const auto [cos, sin] = temporal_rope_shift(*net, shift);
      moved[b].place_sink(cos, sin);
    }
    worst = std::max(worst, test::max_abs(moved[b].k.narrow(2, 0, S), stored[b].k.narrow(2, 0, S)));
    moved_by = std::max(moved_by, test::max_abs(before, stored[b].k.narrow(2, 0, S)));
    worst = std::max(worst, test::max_abs(moved[b].v.narrow(2, 0, S), stored[b].v.narrow(2, 0, S)));
  }
  EXPECT_LT(worst, 1e-5);
  EXPECT_GT(moved_by, 1e-2) << "the position is in the keys";
}

// A stream's frames through a ring with the RoPE angles handed in as tensors (as a replayed CUDA
// graph reads them) equal the frames positioned by frame_offset; the ring reports its slots.
TEST(DitSmall, RopeGivenAsTensorsEqualsFrameOffsetAndRingSlotsTurnOver) {
  test::OneThread one_thread;
  const auto c = DitConfig::small();
  ActionDit net(c);
  default_init_with_actions(*net, 31);
  net->eval();
  torch::NoGradGuard no_grad;
  const int64_t T = 6, H = 8, W = 8, S = (H / 2) * (W / 2), k = c.actions_per_latent_frame;
  const auto in = random_inputs(c, 1, T, H, W, 32);
  std::vector<DitKvCache> by_offset(c.num_blocks), by_tensor(c.num_blocks);
  for (auto& e : by_offset) e.set_ring(/*window=*/2, S, /*sink=*/1);
  for (auto& e : by_tensor) e.set_ring(2, S, 1);
  std::vector<int64_t> slots;
  for (int64_t t = 0; t < T; ++t) {
    slots.push_back(by_tensor[0].ring_slot());
    EXPECT_EQ(by_tensor[0].ring_full(), t >= 2) << "frame " << t;
    const auto expected = net->forward(frame_step(in, t, k, by_offset));
    auto given = frame_step(in, t, k, by_tensor);
    std::tie(given.rope_cos, given.rope_sin) = net->rope_cos_sin(1, H / 2, W / 2, t);  // [S, 1, d]
    EXPECT_TRUE(torch::equal(net->forward(given), expected)) << "frame " << t;
  }
  // Slot 0 holds the sink for good; the other two turn over.
  EXPECT_EQ(slots, (std::vector<int64_t>{0, 1, 2, 1, 2, 1}));
  // A new stream of the same layout reuses the buffers (their addresses are what CUDA graphs hold).
  const void* buffer = by_tensor[0].k.data_ptr();
  by_tensor[0].set_ring(2, S, 0);
  EXPECT_EQ(by_tensor[0].k.data_ptr(), buffer);
  EXPECT_EQ(by_tensor[0].committed_frames(), 0);
  EXPECT_EQ(by_tensor[0].ring_slot(), 0);
  by_tensor[0].set_ring(3, S, 0);
  EXPECT_FALSE(by_tensor[0].k.defined());
  auto wrong = frame_step(in, 0, k, by_tensor);
  wrong.rope_cos = torch::zeros({S + 1, 1, c.model_channels / c.num_heads});
  wrong.rope_sin = wrong.rope_cos;
  EXPECT_NE(test::error_message([&] { net->forward(wrong); }).find("rope_cos"), std::string::npos);
}

// The action scale is applied from a tensor kept with the network, made again when the config's
// scale changes (post-training sets it) and usable for training after an inference-mode forward.
TEST(DitSmall, ActionScaleFollowsTheConfig) {
  test::OneThread one_thread;
  auto c = DitConfig::small();
  ActionDit net(c);
  default_init_with_actions(*net, 41);
  const auto in = random_inputs(c, 1, 3, 8, 8, 42);
  auto scaled_by_hand = in;
  scaled_by_hand.actions = in.actions * 2;
  torch::Tensor unscaled;
  {
    torch::NoGradGuard no_grad;
    unscaled = net->forward(scaled_by_hand);
  }
  net->config.action_scale.assign(static_cast<size_t>(c.action_dim), 2.0);
  {
    c10::InferenceMode inference;
    EXPECT_TRUE(torch::equal(net->forward(in), unscaled));
  }
  auto with_grad = in;  // actions that need a gradient: the product saves the scale for backward
  with_grad.actions = in.actions.clone().requires_grad_(true);
  const auto trained = net->forward(with_grad);  // the same scale with autograd, after inference mode
  // (with gradients the network takes the plain kernels, without them the fused ones: models/dit_kernels.h)
  EXPECT_LT(test::max_abs(trained.detach(), unscaled), 1e-5);
  trained.pow(2).mean().backward();
  net->config.action_scale.assign(static_cast<size_t>(c.action_dim), 1.0);
  torch::NoGradGuard no_grad;
  EXPECT_GT(test::max_abs(net->forward(in), unscaled), 1e-4);
  EXPECT_TRUE(net->action_embedder_B_D->fc1->weight.grad().defined());
  EXPECT_TRUE(with_grad.actions.grad().defined());
}

TEST(DitKvCache, SinkTokensSurviveTrimmingAndArePlacedFromTheirStoredKeys) {
  DitKvCache c;
  const auto entries = torch::arange(1.0, 7.0).view({1, 1, 6, 1}).repeat({1, 1, 1, 2});  // [1, 1, 6, 2]
  c.set_sink(/*tokens=*/1);
  c.append(entries, entries * 10);
  c.keep_last(/*tokens=*/2);
  EXPECT_TRUE(c.k.select(3, 0).flatten().equal(torch::tensor({1.0f, 5.0f, 6.0f})));
  EXPECT_TRUE(c.v.select(3, 0).flatten().equal(torch::tensor({10.0f, 50.0f, 60.0f})));
  const auto half_turn = -torch::ones({2}), none = torch::zeros({2});
  c.place_sink(half_turn, none);  // the sink alone, from its keys as stored
  EXPECT_TRUE(c.k.select(3, 0).flatten().equal(torch::tensor({-1.0f, 5.0f, 6.0f})));
  c.place_sink(half_turn, none);  // again from the stored keys: not a full turn
  EXPECT_TRUE(c.k.select(3, 0).flatten().equal(torch::tensor({-1.0f, 5.0f, 6.0f})));
  c.rotate_keys(half_turn, none);  // every key
  EXPECT_TRUE(c.k.select(3, 0).flatten().equal(torch::tensor({1.0f, -5.0f, -6.0f})));
}

TEST(DitSmall, BlockCausalMaskLayout) {
  const auto m = dit_block_causal_mask(2, 2, /*cached_frames=*/1);  // [4, 6]
  const auto expect =
      torch::tensor({{1, 1, 1, 1, 0, 0}, {1, 1, 1, 1, 0, 0}, {1, 1, 1, 1, 1, 1}, {1, 1, 1, 1, 1, 1}})
          .to(torch::kBool);
  EXPECT_TRUE(torch::equal(m, expect));
  const auto w = dit_block_causal_mask(3, 1, 0, 2);
  EXPECT_TRUE(torch::equal(w, torch::tensor({{1, 0, 0}, {1, 1, 0}, {0, 1, 1}}).to(torch::kBool)));
  const auto sink = dit_block_causal_mask(4, 1, 0, 3, /*sink_frames=*/1);
  EXPECT_TRUE(torch::equal(
      sink, torch::tensor({{1, 0, 0, 0}, {1, 1, 0, 0}, {1, 1, 1, 0}, {1, 0, 1, 1}}).to(torch::kBool)));
}

TEST(DitSmall, InitZeroActionFc2AndReinit) {
  const auto c = DitConfig::small();
  torch::manual_seed(31);
  ActionDit net(c);
  EXPECT_EQ(net->action_embedder_B_D->fc2->weight.abs().sum().item<double>(), 0.0);
  EXPECT_EQ(net->action_embedder_B_3D->fc2->bias.abs().sum().item<double>(), 0.0);
  // nn.Linear default: U(±1/sqrt(fan_in)) for weight and bias.
  const auto w = net->block_list[0]->mlp->layer1->weight;
  EXPECT_LE(w.abs().max().item<double>(), 1.0 / std::sqrt(256.0));
  EXPECT_GT(w.abs().max().item<double>(), 0.9 / std::sqrt(256.0));
  // Zero fc2 => actions do not change the output at init.
  torch::NoGradGuard no_grad;
  auto in = random_inputs(c, 1, 2, 8, 8, 32);
  const auto with = net->forward(in);
  in.actions = torch::Tensor();
  EXPECT_EQ(test::max_abs(net->forward(in), with), 0.0);

  const auto fc1_before = net->action_embedder_B_D->fc1->weight.clone();
  const auto other_before = net->t_embedding->linear_1->weight.clone();
  net->reinit_action_input_layer();
  EXPECT_GT(test::max_abs(net->action_embedder_B_D->fc1->weight, fc1_before), 0.0);
  EXPECT_EQ(test::max_abs(net->t_embedding->linear_1->weight, other_before), 0.0);
}

TEST(DitSmall, InputValidationNamesTheField) {
  const auto c = DitConfig::small();
  ActionDit net(c);
  torch::NoGradGuard no_grad;
  auto in = random_inputs(c, 1, 2, 8, 8, 41);
  in.actions = torch::zeros({1, 3, c.action_dim});
  EXPECT_NE(test::error_message([&] { net->forward(in); }).find("actions"), std::string::npos);
  in = random_inputs(c, 1, 2, 8, 8, 41);
  in.frame_offset = c.max_frames;
  EXPECT_NE(test::error_message([&] { net->forward(in); }).find("frame_offset"), std::string::npos);
}

TEST(DitSmall, PaddingMaskIsResizedToTheLatentGrid) {
  // A pixel-resolution mask is resized (nearest) to the latent H x W, as the reference does.
  const auto c = DitConfig::small();
  torch::manual_seed(45);
  ActionDit net(c);
  torch::NoGradGuard no_grad;
  auto in = random_inputs(c, 1, 2, 8, 8, 46);
  const auto zeros = net->forward(in);
  in.padding_mask = torch::ones({1, 1, 8, 8});
  const auto ones_latent = net->forward(in);
  in.padding_mask = torch::ones({1, 1, 64, 64});
  EXPECT_EQ(test::max_abs(net->forward(in), ones_latent), 0.0);
  EXPECT_GT(test::max_abs(ones_latent, zeros), 1e-3);
}

TEST(DitSmall, TrainsOnFixedTarget) {
  test::OneThread one_thread;
  const auto c = DitConfig::small();
  torch::manual_seed(51);
  ActionDit net(c);
  randomize(*net, 52);  // non-zero action fc2 so every parameter gets a gradient
  // One sample, 2 latent frames of 4x4 (8 tokens): keeps 30 steps at a few seconds on one core.
  const auto in = random_inputs(c, 1, 2, 4, 4, 53);
  const auto target = torch::randn({1, c.out_channels, 2, 4, 4});
  torch::optim::Adam opt(net->parameters(), torch::optim::AdamOptions(1e-3));
  double first = 0, last = 0;
  for (int step = 0; step < 30; ++step) {
    opt.zero_grad();
    const auto loss = (net->forward(in) - target).pow(2).mean();
    loss.backward();
    if (step == 0) {
      for (const auto& item : net->named_parameters()) {
        const auto& g = item.value().grad();
        EXPECT_TRUE(g.defined() && g.abs().sum().item<double>() > 0) << item.key();
      }
    }
    opt.step();
    (step == 0 ? first : last) = loss.item<double>();
  }
  EXPECT_LT(last, 0.5 * first);
}

// Timing of the DojoSim demo size; run with --gtest_also_run_disabled_tests (no assertions on time).
TEST(DitSmall, DISABLED_TimeForwardBackward) {
  const auto c = DitConfig::small();
  ActionDit net(c);
  const auto in = random_inputs(c, 4, 4, 8, 8, 61);
  auto time_ms = [](const std::function<void()>& fn) {
    fn();  // warm-up
    const int reps = 10;
    const auto t0 = std::chrono::steady_clock::now();
    for (int i = 0; i < reps; ++i) fn();
    return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count() / reps;
  };
  const int saved_threads = torch::get_num_threads();
  for (int threads : {1, 2}) {
    torch::set_num_threads(threads);
    const double fwd = time_ms([&] {
      torch::NoGradGuard no_grad;
      net->forward(in);
    });
    const double fwd_bwd = time_ms([&] {
      net->zero_grad();
      net->forward(in).pow(2).mean().backward();
    });
    std::printf("DiT small B=4 T=4 8x8, %d threads: forward %.1f ms, forward+backward %.1f ms (%ld params)\n",
                threads, fwd, fwd_bwd, static_cast<long>(net->num_parameters()));
  }
  torch::set_num_threads(saved_threads);
}

}  // namespace dojo::models
