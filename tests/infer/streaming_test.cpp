#include "infer/streaming.h"

#include <gtest/gtest.h>
#include <torch/torch.h>

#include "core/error.h"
#include "test_util.h"
#include "train/wm_test_fixtures.h"

namespace dojo::infer {
namespace {

// A random student (live action MLPs, so actions matter) and tiny tokenizer, shared weights
// across engines built from the same seed.
StreamingEngine engine(StreamingEngine::Options o, uint64_t seed = 0) {
  torch::manual_seed(seed);
  models::ActionDit net(train::test_fixtures::tiny_dit(/*live_actions=*/true, /*width=*/64));
  models::WanVae vae(models::WanVaeConfig::tiny());
  return StreamingEngine(net, vae, o);
}

torch::Tensor actions_for(int64_t steps, int64_t batch, uint64_t seed) {
  auto g = train::test_fixtures::gen(seed);
  return torch::rand({batch, 4 * steps, 384}, g) * 2 - 1;  // [B, 4 steps, 384]
}

std::vector<torch::Tensor> run(StreamingEngine& e, const torch::Tensor& first, const torch::Tensor& actions,
                               uint64_t seed) {
  e.reset(first, seed);
  std::vector<torch::Tensor> out;
  for (int64_t s = 0; s < actions.size(1) / 4; ++s) out.push_back(e.step(actions.narrow(1, 4 * s, 4)));
  return out;
}

// Inference mode changes the dispatch, not the numbers; what the engine hands back is an ordinary
// tensor that callers may modify in place and train on.
TEST(Streaming, InferenceModeGivesTheSameFramesAsOrdinaryTensors) {
  test::OneThread one;
  StreamingEngine::Options o;
  o.student.window_frames = 2;
  auto fast = engine(o);
  o.inference_mode = false;
  auto plain = engine(o);
  const auto first = torch::randint(0, 255, {1, 32, 32, 3}, torch::kByte);
  const auto actions = actions_for(3, 1, 3);
  auto a = run(fast, first, actions, 5);
  const auto b = run(plain, first, actions, 5);
  for (size_t i = 0; i < a.size(); ++i) {
    EXPECT_TRUE(torch::equal(a[i], b[i])) << "step " << i;
    EXPECT_FALSE(a[i].is_inference());
  }
  a[0].zero_();  // in place outside inference mode: refused for inference tensors
  const auto weight = torch::ones({1}, torch::requires_grad());
  (a[1].to(torch::kFloat32) * weight).sum().backward();  // saved for backward: likewise
  EXPECT_GT(weight.grad().item<double>(), 0);
  EXPECT_FALSE(fast.reset(first, 5).is_inference());
}

// bf16 streaming with the linear and convolution weights stored in bf16 once is as close to fp32
// as autocast casting the float32 weights at every op (not bit-equal: on the CPU autocast rounds a
// 3-D linear's bias differently), latents and decoded frames alike.
TEST(Streaming, Bf16WeightsCastOnceAreAsAccurateAsAutocastCastingThemEachOp) {
  test::OneThread one;
  torch::manual_seed(0);  // the start frame: the ratio below is a measurement on fixed inputs
  const auto relative = [](const torch::Tensor& a, const torch::Tensor& b) {
    const auto x = a.to(torch::kFloat64), y = b.to(torch::kFloat64);
    return ((x - y).norm() / y.norm()).item<double>();
  };
  const auto first = torch::randint(0, 255, {1, 32, 32, 3}, torch::kByte);
  const auto actions = actions_for(4, 1, 3);
  for (const bool decode : {false, true}) {
    StreamingEngine::Options o;
    o.decode = decode;
    o.student.window_frames = 2;
    o.precision = Precision::kBFloat16;
    auto cast = engine(o);
    o.cast_weights = false;
    auto per_op = engine(o);
    o.precision = Precision::kFloat32;
    auto fp32 = engine(o);
    EXPECT_EQ(cast.net()->block_list[0]->self_attn->q_proj->weight.scalar_type(), torch::kBFloat16);
    EXPECT_EQ(cast.tokenizer()->parameters()[0].scalar_type(), torch::kBFloat16);
    EXPECT_EQ(cast.net()->t_embedding_norm->weight.scalar_type(), torch::kFloat32);  // not a matmul
    EXPECT_EQ(per_op.net()->block_list[0]->self_attn->q_proj->weight.scalar_type(), torch::kFloat32);
    const auto a = run(cast, first, actions, 5), b = run(per_op, first, actions, 5),
               c = run(fp32, first, actions, 5);
    for (size_t i = 0; i < a.size(); ++i) {
      const double cast_error = relative(a[i], c[i]), autocast_error = relative(b[i], c[i]);
      EXPECT_GT(autocast_error, 0) << "the bf16 rows ran in bf16";
      EXPECT_LT(cast_error, (decode ? 0.1 : 0.01)) << "step " << i;
      EXPECT_LT(cast_error, 1.5 * autocast_error) << "step " << i << (decode ? " (frames)" : " (latents)");
    }
  }
}

// The ring-buffer KV cache against recomputing the whole history under the block-causal window
// mask, past the point where the ring wraps (window 2, 7 new frames).
TEST(Streaming, CachedEqualsBlockCausalRecomputation) {
  test::OneThread one;
  StreamingEngine::Options o;
  o.decode = false;
  o.student.window_frames = 2;
  auto cached = engine(o);
  o.use_cache = false;
  auto reference = engine(o);
  const auto first = torch::randint(0, 255, {2, 32, 32, 3}, torch::kByte);
  const auto actions = actions_for(7, 2, 3);
  const auto a = run(cached, first, actions, 5);
  const auto b = run(reference, first, actions, 5);
  ASSERT_EQ(a.size(), b.size());
  double worst = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    EXPECT_EQ(a[i].sizes(), (std::vector<int64_t>{2, 16, 1, 4, 4}));
    worst = std::max(worst, (a[i] - b[i]).abs().max().item<double>());
  }
  EXPECT_LT(worst, 1e-4);
  std::printf("cached vs recomputed, 7 frames, window 2: max abs %.2g\n", worst);
  EXPECT_EQ(cached.latent_frames(), 8);

  // With an attention sink at its own position, frame 0 stays in the mask of every frame.
  o.student.sink_frames = 1;
  o.student.sink_position = SinkPosition::kAbsolute;
  auto sink_reference = engine(o);
  o.use_cache = true;
  auto sink_cached = engine(o);
  const auto sa = run(sink_cached, first, actions, 5);
  const auto sb = run(sink_reference, first, actions, 5);
  double sink_worst = 0;
  for (size_t i = 0; i < sa.size(); ++i)
    sink_worst = std::max(sink_worst, (sa[i] - sb[i]).abs().max().item<double>());
  EXPECT_LT(sink_worst, 1e-4);
  EXPECT_LT((sa[1] - a[1]).abs().max().item<double>(), 1e-5) << "frame 0 still in the window";
  EXPECT_GT((sa[4] - a[4]).abs().max().item<double>(), 1e-3) << "frame 0 kept past the window";
  o.student.sink_frames = 0;

  // The window matters (so the comparison above can fail): a longer window changes frame 4 on.
  o.use_cache = true;
  o.student.window_frames = 6;
  auto wide = engine(o);
  const auto c = run(wide, first, actions, 5);
  EXPECT_LT((c[1] - a[1]).abs().max().item<double>(), 1e-4) << "frames within both windows agree";
  EXPECT_GT((c[5] - a[5]).abs().max().item<double>(), 1e-3);
}

TEST(Streaming, FramesFollowSeedAndActionsWithFlatMemory) {
  test::OneThread one;
  StreamingEngine::Options o;
  o.student.window_frames = 2;
  auto e = engine(o);
  const auto first = torch::randint(0, 255, {1, 32, 32, 3}, torch::kByte);
  const auto frame0 = e.reset(first, 1);
  ASSERT_EQ(frame0.sizes(), (std::vector<int64_t>{1, 1, 32, 32, 3}));
  const auto round_trip = models::reconstruct_frames(e.tokenizer(), first.unsqueeze(1));  // [1, 1, H, W, 3]
  EXPECT_LE((frame0.to(torch::kInt) - round_trip.to(torch::kInt)).abs().max().item<int>(), 1);

  const auto actions = actions_for(12, 1, 4);
  const auto a = run(e, first, actions, 9);
  ASSERT_EQ(a[0].sizes(), (std::vector<int64_t>{1, 4, 32, 32, 3}));
  EXPECT_EQ(a[0].scalar_type(), torch::kUInt8);
  const auto b = run(e, first, actions, 9);
  for (size_t i = 0; i < a.size(); ++i)
    EXPECT_TRUE(a[i].equal(b[i])) << "reset + same seed = same video, step " << i;
  const auto other = run(e, first, actions_for(12, 1, 5), 9);
  EXPECT_FALSE(other[3].equal(a[3])) << "other actions, other frames";

  // The ring holds window + 1 frames from the moment it fills: the same bytes at every later step.
  e.reset(first, 9);
  std::vector<int64_t> bytes;
  for (int64_t s = 0; s < 12; ++s) {
    e.step(actions.narrow(1, 4 * s, 4));
    bytes.push_back(e.cache_bytes());
    EXPECT_GT(e.last_timings().total_ms, 0);
  }
  EXPECT_GT(bytes.front(), 0);
  for (auto b : bytes) EXPECT_EQ(b, bytes.front());
  EXPECT_THROW(e.step(torch::zeros({1, 3, 384})), Error);
}

// Past the network's RoPE table (max_frames) the engine moves every position back together: the
// frames equal those of a network with a longer table.
TEST(Streaming, AnyHorizonRebasesRopePositions) {
  test::OneThread one;
  StreamingEngine::Options o;
  o.decode = false;
  o.student.window_frames = 2;
  auto config = train::test_fixtures::tiny_dit(/*live_actions=*/true, /*width=*/64);
  config.max_img_h = config.max_img_w = 8;  // the table's length is max(h, w, frames) / patch
  const auto make = [&](int64_t max_frames) {
    config.max_frames = max_frames;
    torch::manual_seed(0);
    models::ActionDit net(config);
    models::WanVae vae(models::WanVaeConfig::tiny());
    return StreamingEngine(net, vae, o);
  };
  const auto first = torch::randint(0, 255, {1, 32, 32, 3}, torch::kByte);
  const auto actions = actions_for(14, 1, 6);
  for (int64_t window : {2, 0}) {  // window 0: the new frame alone, still with its actions
    o.student.window_frames = window;
    auto short_table = make(6), long_table = make(64);
    ASSERT_EQ(short_table.net()->pos_embedder->seq.size(0), 6);
    const auto a = run(short_table, first, actions, 2);
    const auto b = run(long_table, first, actions, 2);
    double worst = 0;
    for (size_t i = 0; i < a.size(); ++i) worst = std::max(worst, (a[i] - b[i]).abs().max().item<double>());
    EXPECT_LT(worst, 1e-4) << "window " << window;
    std::printf("window %ld: rebased (RoPE table 6) vs absolute positions, 14 frames: max abs %.2g\n",
                static_cast<long>(window), worst);
  }
  o.student.window_frames = 5;  // no room left in a table of 6
  EXPECT_THROW(make(6), Error);
}

// A sink at the window's edge takes the positions of the frames it replaces: the same frames as a
// sink at its own position while frame 0 is still in the window, others after; RoPE rebasing and
// memory as without a sink.
TEST(Streaming, WindowEdgeSinkMovesWithTheWindow) {
  test::OneThread one;
  StreamingEngine::Options o;
  o.decode = false;
  o.student.window_frames = 2;
  o.student.sink_frames = 1;
  auto config = train::test_fixtures::tiny_dit(/*live_actions=*/true, /*width=*/64);
  config.max_img_h = config.max_img_w = 8;
  const auto make = [&](int64_t max_frames, SinkPosition position) {
    config.max_frames = max_frames;
    o.student.sink_position = position;
    torch::manual_seed(0);
    return StreamingEngine(models::ActionDit(config), models::WanVae(models::WanVaeConfig::tiny()), o);
  };
  const auto first = torch::randint(0, 255, {1, 32, 32, 3}, torch::kByte);
  const auto actions = actions_for(14, 1, 6);
  auto edge = make(64, SinkPosition::kWindowEdge), absolute = make(64, SinkPosition::kAbsolute);
  const auto a = run(edge, first, actions, 2);
  const auto b = run(absolute, first, actions, 2);
  EXPECT_LT((a[1] - b[1]).abs().max().item<double>(), 1e-5) << "frame 2 sees frame 0 where it is";
  EXPECT_GT((a[2] - b[2]).abs().max().item<double>(), 1e-3) << "frame 3 sees it one frame later";

  for (auto position : {SinkPosition::kWindowEdge, SinkPosition::kAbsolute}) {
    auto rebased = make(6, position);  // rebased every few frames
    const auto c = run(rebased, first, actions, 2);
    const auto& expected = position == SinkPosition::kWindowEdge ? a : b;
    double worst = 0;
    for (size_t i = 0; i < a.size(); ++i)
      worst = std::max(worst, (expected[i] - c[i]).abs().max().item<double>());
    EXPECT_LT(worst, 1e-4) << to_string(position);
    std::printf("%s sink, RoPE table 6 vs 64, 14 frames: max abs %.2g\n", to_string(position), worst);
  }

  // A window of 2 with a sink of 2: the first two frames and the new one, for good.
  o.student.sink_frames = 2;
  auto whole = make(64, SinkPosition::kAbsolute);
  o.use_cache = false;
  auto whole_reference = make(64, SinkPosition::kAbsolute);
  o.use_cache = true;
  const auto w1 = run(whole, first, actions, 2), w2 = run(whole_reference, first, actions, 2);
  double whole_worst = 0;
  for (size_t i = 0; i < w1.size(); ++i)
    whole_worst = std::max(whole_worst, (w1[i] - w2[i]).abs().max().item<double>());
  EXPECT_LT(whole_worst, 1e-4);

  auto student = edge.options().student;
  student.sink_frames = 3;  // more than the window
  EXPECT_THROW(edge.set_student(student), Error);
  student.sink_frames = 1;
  student.action_alignment = ActionAlignment::kReleasedOffline;
  EXPECT_THROW(edge.set_student(student), Error);
  o.use_cache = false;
  o.student.sink_frames = 1;
  EXPECT_THROW(make(64, SinkPosition::kWindowEdge), Error) << "needs the cache";
  EXPECT_NO_THROW(make(64, SinkPosition::kAbsolute));
}

TEST(Streaming, DecodesWithTheFastDecoderWhenGiven) {
  test::OneThread one;
  StreamingEngine::Options o;
  models::FastDecoderConfig fc;
  fc.widths = {16, 12, 8};
  fc.blocks = {1, 1, 1};
  fc.head_width = 8;
  o.fast_decoder = models::FastDecoder(fc);
  auto e = engine(o);
  const auto first = torch::randint(0, 255, {1, 32, 32, 3}, torch::kByte);
  const auto video = e.rollout(first, actions_for(3, 1, 2), 4);
  EXPECT_EQ(video.sizes(), (std::vector<int64_t>{1, 13, 32, 32, 3}));
  // Frame 0 as the fast decoder shows the first latent (not the Wan round trip).
  models::FastDecoderState state;
  torch::NoGradGuard no_grad;
  const auto z0 = e.tokenizer()->encode_latents(models::video_to_model(first.unsqueeze(1)));
  const auto expect = models::model_to_video(o.fast_decoder->step(z0.select(2, 0), state).clamp(-1, 1));
  EXPECT_TRUE(video.narrow(1, 0, 1).equal(expect));
}

// On a GPU the hops of a full window are replayed from a CUDA graph per ring slot: the latents are
// those of the eager path, bit for bit, in fp32 and bf16, with both alignments the graphs take, as
// the ring turns over, across RoPE rebases (a table of 6 frames) and a second stream on the same
// buffers.
TEST(Streaming, CudaGraphsReplayTheEagerLatents_CUDA) {
  DOJO_REQUIRE_CUDA();
  if (!CapturedCall::available()) GTEST_SKIP() << "built without CUDA graphs";
  auto config = train::test_fixtures::tiny_dit(/*live_actions=*/true, /*width=*/64);
  config.max_img_h = config.max_img_w = 8;
  config.max_frames = 6;  // rebases from the 6th latent frame on
  const auto first = torch::randint(0, 255, {1, 32, 32, 3}, torch::kByte);
  const int64_t window = 2, steps = 2 * window + 5;
  const auto actions = actions_for(steps, 1, 6);
  for (const auto alignment : {ActionAlignment::kTraining, ActionAlignment::kReleasedOffline}) {
    for (const auto precision : {Precision::kFloat32, Precision::kBFloat16}) {
      StreamingEngine::Options o;
      o.device = torch::Device(torch::kCUDA, 0);
      o.precision = precision;
      o.decode = false;
      o.student.window_frames = window;
      o.student.sink_frames = alignment == ActionAlignment::kTraining ? 1 : 0;
      o.student.action_alignment = alignment;
      torch::manual_seed(0);
      models::ActionDit net(config);
      models::WanVae vae(models::WanVaeConfig::tiny());
      o.cuda_graphs = false;
      StreamingEngine eager(net, vae, o);
      o.cuda_graphs = true;
      StreamingEngine graphed(net, vae, o);
      ASSERT_TRUE(graphed.graphs_enabled());
      for (int pass = 0; pass < 2; ++pass) {
        const auto a = run(eager, first, actions, 8 + pass), b = run(graphed, first, actions, 8 + pass);
        for (size_t i = 0; i < a.size(); ++i)
          EXPECT_TRUE(torch::equal(a[i], b[i])) << to_string(alignment) << " pass " << pass << " step " << i;
      }
      // Steps with a full window (from step `window` on) replay: 2 passes of steps - window + 1.
      EXPECT_EQ(graphed.graph_replays(), 2 * (steps - window + 1));
      EXPECT_EQ(eager.graph_replays(), 0);
    }
  }
}

// The released offline script's alignment: the first w latents use their own chunks, later ones
// are generated with chunk k - (w - 1) and cached with their own; the cached path and the plain
// reference implement it alike.
TEST(Streaming, ReleasedOfflineAlignmentLagsTwoChunks) {
  test::OneThread one;
  StreamingEngine::Options o;
  o.decode = false;
  o.student.window_frames = 3;
  auto training = engine(o);
  o.student.action_alignment = ActionAlignment::kReleasedOffline;
  auto offline = engine(o);
  o.use_cache = false;
  auto offline_reference = engine(o);
  const auto first = torch::randint(0, 255, {1, 32, 32, 3}, torch::kByte);
  auto actions = actions_for(6, 1, 11);
  const auto t = run(training, first, actions, 2);
  const auto a = run(offline, first, actions, 2);
  const auto r = run(offline_reference, first, actions, 2);
  for (size_t k = 0; k < a.size(); ++k) EXPECT_LT((a[k] - r[k]).abs().max().item<double>(), 1e-4) << k;
  for (size_t k = 0; k < 3; ++k) EXPECT_TRUE(a[k].equal(t[k])) << "latent " << k + 1 << " uses its own chunk";
  EXPECT_GT((a[3] - t[3]).abs().max().item<double>(), 1e-3) << "latent 4 is generated with chunk 2";

  // The last latent never sees its own chunk; in the training alignment it does.
  actions.narrow(1, 20, 4).uniform_(-1, 1);
  const auto t2 = run(training, first, actions, 2);
  const auto a2 = run(offline, first, actions, 2);
  EXPECT_TRUE(a2[5].equal(a[5]));
  EXPECT_GT((t2[5] - t[5]).abs().max().item<double>(), 1e-3);
}

// The released teleop script's alignment: 12 actions per step; the first step makes 3 latents
// with their own chunks, later steps re-store the context with the fresh chunks 0 and 1, generate
// with fresh chunk 0 and drop chunk 2.
TEST(Streaming, ReleasedTeleopAlignmentRecachesWithFreshActions) {
  test::OneThread one;
  StreamingEngine::Options o;
  o.decode = false;
  o.student.window_frames = 3;
  auto training = engine(o);
  o.student.action_alignment = ActionAlignment::kReleasedTeleop;
  auto teleop = engine(o);
  EXPECT_EQ(teleop.actions_per_step(), 12);
  const auto first = torch::randint(0, 255, {1, 32, 32, 3}, torch::kByte);
  const auto chunks = actions_for(3, 1, 12);
  const auto t = run(training, first, chunks, 4);
  teleop.reset(first, 4);
  const auto boot = teleop.step(chunks);  // [1, 16, 3, h, w]
  ASSERT_EQ(boot.size(2), 3);
  EXPECT_TRUE(boot.equal(torch::cat(t, 2))) << "the first step is the training rollout of 3 latents";
  EXPECT_THROW(teleop.step(chunks.narrow(1, 0, 4)), Error);

  const auto steady = [&](const torch::Tensor& fresh) {
    teleop.reset(first, 4);
    teleop.step(chunks);
    return teleop.step(fresh);  // [1, 16, 1, h, w]
  };
  auto fresh = actions_for(3, 1, 13);
  const auto base = steady(fresh);
  ASSERT_EQ(base.size(2), 1);
  auto dropped = fresh.clone();
  dropped.narrow(1, 8, 4).uniform_(-1, 1);
  EXPECT_TRUE(steady(dropped).equal(base)) << "fresh chunk 2 is dropped";
  auto context = fresh.clone();
  context.narrow(1, 4, 4).uniform_(-1, 1);
  EXPECT_GT((steady(context) - base).abs().max().item<double>(), 1e-3) << "chunk 1 re-caches the context";
  EXPECT_EQ(teleop.cache_bytes() > 0, true);

  o.use_cache = false;
  EXPECT_THROW(engine(o), Error) << "teleop re-writes the cache: it needs one";
}

TEST(StudentConfig, BadFieldsNameTheFile) {
  EXPECT_THROW(StudentConfig::from_json({{"steps", 5}}, "ck/config.json"), Error);
  try {
    StudentConfig::from_json({{"window_frames", -1}}, "ck/config.json");
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("ck/config.json: field 'student.window_frames'"), std::string::npos);
  }
  try {
    StudentConfig::from_json({{"action_alignment", "lagged"}}, "ck/config.json");
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("field 'student.action_alignment'"), std::string::npos);
  }
  const auto c = StudentConfig::from_json(
      {{"steps", 2}, {"bf16_times", false}, {"action_alignment", "released_offline"}}, "x");
  EXPECT_EQ(c.action_alignment, ActionAlignment::kReleasedOffline);
  EXPECT_EQ(c.schedule().size(), 2u);
  EXPECT_EQ(StudentConfig::from_json(c.to_json(), "x").to_json(), c.to_json());
  EXPECT_THROW(StudentConfig::from_json({{"sink_position", "first"}}, "x"), Error);
  EXPECT_THROW(StudentConfig::from_json({{"sink_frames", -1}}, "x"), Error);
  const auto sink = StudentConfig::from_json({{"sink_frames", 1}, {"sink_position", "absolute"}}, "x");
  EXPECT_EQ(sink.sink_position, SinkPosition::kAbsolute);
  EXPECT_EQ(StudentConfig::from_json(sink.to_json(), "x").to_json(), sink.to_json());
  EXPECT_EQ(StudentConfig::from_json(nlohmann::json::object(), "x").sink_frames, 0) << "released: no sink";
}

}  // namespace
}  // namespace dojo::infer
