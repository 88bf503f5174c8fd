// safetensors reader/writer: byte-exact round trips for every dtype, the exact on-disk format,
// metadata, zero-copy views, validation errors, and the golden fixtures written by Python.
#include "core/safetensors.h"

#include <cstring>
#include <fstream>
#include <functional>
#include <iterator>
#include <regex>
#include <set>
#include <sstream>

#include "core/error.h"
#include "test_util.h"

namespace dojo {
namespace {

void write_bytes(const std::filesystem::path& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

std::string le64(uint64_t n) {
  std::string out(8, '\0');
  for (int i = 0; i < 8; ++i, n >>= 8) out[i] = static_cast<char>(n & 0xff);
  return out;
}

// A file made by hand: header text (unpadded unless the caller pads it) then data.
std::string raw_file(const std::string& header, const std::string& data) {
  return le64(header.size()) + header + data;
}

std::string tensor_bytes(const torch::Tensor& t) {
  const torch::Tensor c = t.contiguous();
  return std::string(static_cast<const char*>(c.data_ptr()), c.numel() * c.element_size());
}

// Every bit pattern is fair game for the float dtypes (NaN payloads, -0, inf, denormals): the
// values are random integers reinterpreted.
torch::Tensor random_tensor(torch::ScalarType type, std::vector<int64_t> shape) {
  switch (type) {
    case torch::kFloat64:
      return torch::randint(INT64_MIN, INT64_MAX, shape, torch::kInt64).view(torch::kFloat64);
    case torch::kFloat32:
      return torch::randint(INT32_MIN, INT32_MAX, shape, torch::kInt32).view(torch::kFloat32);
    case torch::kFloat16:
    case torch::kBFloat16:
      return torch::randint(INT16_MIN, INT16_MAX, shape, torch::kInt16).view(type);
    case torch::kBool:
      return torch::randint(0, 2, shape, torch::kInt64).to(torch::kBool);
    case torch::kUInt8:
      return torch::randint(0, 256, shape, torch::kInt64).to(torch::kUInt8);
    case torch::kInt8:
      return torch::randint(-128, 128, shape, torch::kInt64).to(torch::kInt8);
    default:
      return torch::randint(-1000000, 1000000, shape, torch::kInt64).to(type);
  }
}

const std::vector<std::pair<torch::ScalarType, std::string>> kDtypes = {
    {torch::kFloat64, "F64"}, {torch::kFloat32, "F32"}, {torch::kFloat16, "F16"}, {torch::kBFloat16, "BF16"},
    {torch::kInt64, "I64"},   {torch::kInt32, "I32"},   {torch::kInt16, "I16"},   {torch::kInt8, "I8"},
    {torch::kUInt8, "U8"},    {torch::kBool, "BOOL"}};

// Expects `fn` to throw dojo::Error whose message contains every one of `needles`.
void expect_error(const std::function<void()>& fn, std::initializer_list<std::string> needles) {
  const std::string message = test::error_message(fn);
  for (const auto& needle : needles)
    EXPECT_NE(message.find(needle), std::string::npos) << message << "\n  lacks: " << needle;
  EXPECT_EQ(message.find('\n'), std::string::npos) << message;
}

TEST(Safetensors, RoundTripEveryDtypeIsByteExact) {
  torch::manual_seed(7);
  test::TempDir dir;
  NamedTensors tensors;
  for (const auto& [type, name] : kDtypes) {
    tensors.emplace_back(name + ".matrix", random_tensor(type, {3, 5}));
    tensors.emplace_back(name + ".scalar", random_tensor(type, {}));
    tensors.emplace_back(name + ".empty", random_tensor(type, {0, 4}));
    tensors.emplace_back(name + ".transposed", random_tensor(type, {4, 6}).t());  // non-contiguous input
    tensors.emplace_back(name + ".odd", random_tensor(type, {7}));                // leaves odd offsets behind
  }
  const Metadata metadata = {{"format", "pt"}, {"note", "every dtype"}};
  save_safetensors(dir / "a.safetensors", tensors, metadata);

  const auto file = SafetensorsFile::open(dir / "a.safetensors");
  ASSERT_EQ(file.keys().size(), tensors.size());
  for (size_t i = 0; i < tensors.size(); ++i) {
    const auto& [name, original] = tensors[i];
    SCOPED_TRACE(name);
    EXPECT_EQ(file.keys()[i], name);  // insertion order kept
    const TensorInfo& info = file.info(name);
    EXPECT_EQ(info.dtype, safetensors_dtype(original.scalar_type()));
    EXPECT_EQ(info.shape, original.sizes().vec());
    const auto [raw, size] = file.raw(name);
    const std::string expected = tensor_bytes(original);
    ASSERT_EQ(size, expected.size());
    if (size > 0) {
      EXPECT_EQ(std::memcmp(raw, expected.data(), size), 0);
    }
    for (const bool copy : {false, true}) {
      const torch::Tensor loaded = file.tensor(name, copy);
      EXPECT_EQ(loaded.scalar_type(), original.scalar_type());
      EXPECT_EQ(loaded.sizes(), original.sizes());
      EXPECT_EQ(tensor_bytes(loaded), expected);  // bitwise, so NaN payloads count too
      if (!torch::isFloatingType(original.scalar_type())) {
        EXPECT_TRUE(torch::equal(loaded, original));
      }
    }
  }

  // Same input, same bytes; and what was read writes back to the very same file.
  save_safetensors(dir / "b.safetensors", tensors, metadata);
  save_safetensors(dir / "c.safetensors", file.tensors(), file.metadata());
  const std::string a = test::read_file(dir / "a.safetensors");
  EXPECT_EQ(test::read_file(dir / "b.safetensors"), a);
  EXPECT_EQ(test::read_file(dir / "c.safetensors"), a);
}

TEST(Safetensors, ExactOnDiskFormat) {
  test::TempDir dir;
  const auto a = torch::tensor({1.0f, -2.0f});
  const auto b = torch::tensor({int64_t{3}}, torch::kInt64).reshape({1, 1});
  save_safetensors(dir / "f.safetensors", {{"b", b}, {"a", a}}, {{"z", "1"}, {"k", "v"}});

  std::string header =
      R"({"b":{"dtype":"I64","shape":[1,1],"data_offsets":[0,8]},"a":{"dtype":"F32","shape":[2],"data_offsets":[8,16]},)"
      R"("__metadata__":{"z":"1","k":"v"}})";
  header.append((8 - (8 + header.size()) % 8) % 8, ' ');
  EXPECT_EQ(test::read_file(dir / "f.safetensors"), raw_file(header, tensor_bytes(b) + tensor_bytes(a)));
  EXPECT_EQ((8 + header.size()) % 8, 0u);

  // No metadata: no "__metadata__" entry at all.
  save_safetensors(dir / "g.safetensors", {{"a", a}});
  std::string bare = R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]}})";
  bare.append((8 - (8 + bare.size()) % 8) % 8, ' ');
  EXPECT_EQ(test::read_file(dir / "g.safetensors"), raw_file(bare, tensor_bytes(a)));
}

TEST(Safetensors, MetadataRoundTripKeepsOrderAndText) {
  test::TempDir dir;
  Metadata metadata;
  metadata["zeta"] = "last letter first";
  metadata["config"] = R"({"dim": 64, "name": "tiny \"quoted\""})";
  metadata["unicode"] = "α → β, 日本";
  metadata["newline"] = "a\nb\tc";
  metadata["empty"] = "";
  save_safetensors(dir / "m.safetensors", {{"x", torch::zeros({2})}}, metadata);
  const auto file = SafetensorsFile::open(dir / "m.safetensors");
  ASSERT_EQ(file.metadata().size(), metadata.size());
  size_t i = 0;
  for (const auto& [key, value] : metadata) {
    EXPECT_EQ(file.metadata().begin()[i].first, key);
    EXPECT_EQ(file.metadata().at(key), value);
    ++i;
  }
  EXPECT_EQ(nlohmann::json::parse(file.metadata().at("config"))["dim"], 64);
}

TEST(Safetensors, ViewsAreCopyOnWriteAndOutliveTheFileObject) {
  test::TempDir dir;
  save_safetensors(dir / "v.safetensors", {{"w", torch::arange(8, torch::kFloat32)}});
  const std::string before = test::read_file(dir / "v.safetensors");
  torch::Tensor view;
  {
    const auto file = SafetensorsFile::open(dir / "v.safetensors");
    view = file.tensor("w");
    const auto [raw, size] = file.raw("w");
    EXPECT_EQ(view.data_ptr(), static_cast<const void*>(raw));  // zero-copy
    const torch::Tensor copy = file.tensor("w", /*copy=*/true);
    EXPECT_NE(copy.data_ptr(), view.data_ptr());
    view.mul_(2);  // writes into private pages
    EXPECT_TRUE(torch::equal(copy, torch::arange(8, torch::kFloat32)));
  }
  EXPECT_TRUE(torch::equal(view, torch::arange(8, torch::kFloat32) * 2));  // mapping still alive
  EXPECT_EQ(test::read_file(dir / "v.safetensors"), before);               // the file never changes
  EXPECT_TRUE(torch::equal(SafetensorsFile::open(dir / "v.safetensors").tensor("w"),
                           torch::arange(8, torch::kFloat32)));
}

TEST(Safetensors, MisalignedDataIsCopied) {
  // An unpadded header puts F32 data at an odd address; reading must still be right.
  test::TempDir dir;
  const auto x = torch::tensor({1.5f, 2.5f, -3.0f});
  const std::string header = R"({"x":{"dtype":"F32","shape":[3],"data_offsets":[0,12]}})";
  ASSERT_NE((8 + header.size()) % 4, 0u);
  write_bytes(dir / "u.safetensors", raw_file(header, tensor_bytes(x)));
  EXPECT_TRUE(torch::equal(SafetensorsFile::open(dir / "u.safetensors").tensor("x"), x));
}

TEST(Safetensors, DtypesWithoutTorchTypeAreListedButNotLoaded) {
  test::TempDir dir;
  const std::string header =
      R"({"u":{"dtype":"U16","shape":[2],"data_offsets":[0,4]},"f":{"dtype":"F8_E4M3","shape":[4],"data_offsets":[4,8]}})";
  write_bytes(dir / "x.safetensors", raw_file(header, std::string(8, '\1')));
  const auto file = SafetensorsFile::open(dir / "x.safetensors");
  EXPECT_EQ(file.info("u").dtype, "U16");
  EXPECT_FALSE(file.info("u").scalar_type.has_value());
  EXPECT_EQ(file.num_elements(), 6);
  expect_error([&] { file.tensor("u"); }, {"x.safetensors", "'u'", "U16"});
}

TEST(Safetensors, MalformedFilesNameTheFileAndTensor) {
  test::TempDir dir;
  auto check = [&](const std::string& name, const std::string& bytes,
                   std::initializer_list<std::string> needles) {
    SCOPED_TRACE(name);
    write_bytes(dir / name, bytes);
    std::vector<std::string> all(needles);
    all.push_back(name);
    const std::string message = test::error_message([&] { SafetensorsFile::open(dir / name); });
    for (const auto& needle : all)
      EXPECT_NE(message.find(needle), std::string::npos) << message << " lacks " << needle;
  };
  const std::string f8(8, '\0');
  check("short.safetensors", "abc", {"too short"});
  check("huge_len.safetensors", le64(1ull << 40) + "{}", {"header length"});
  check("len_past_end.safetensors", le64(100) + "{}", {"header length"});
  check("not_json.safetensors", raw_file("{not json}", ""), {"not valid JSON"});
  check("not_object.safetensors", raw_file("[1, 2]  ", ""), {"not"});
  check("bad_dtype.safetensors", raw_file(R"({"w":{"dtype":"Q7","shape":[2],"data_offsets":[0,8]}})", f8),
        {"'w'", "Q7"});
  check("size_mismatch.safetensors",
        raw_file(R"({"w":{"dtype":"F32","shape":[3],"data_offsets":[0,8]}})", f8), {"'w'", "needs"});
  check("negative_dim.safetensors",
        raw_file(R"({"w":{"dtype":"F32","shape":[-2],"data_offsets":[0,8]}})", f8), {"'w'", "shape"});
  check("out_of_range.safetensors",
        raw_file(R"({"w":{"dtype":"F32","shape":[4],"data_offsets":[0,16]}})", f8),
        {"'w'", "beyond the end", "truncated"});
  check("end_before_begin.safetensors",
        raw_file(R"({"w":{"dtype":"U8","shape":[0],"data_offsets":[8,0]}})", f8),
        {"'w'", "end before begin"});
  check("missing_offsets.safetensors", raw_file(R"({"w":{"dtype":"F32","shape":[2]}})", f8),
        {"'w'", "data_offsets"});
  check(
      "overlap.safetensors",
      raw_file(
          R"({"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]},"b":{"dtype":"F32","shape":[1],"data_offsets":[4,8]}})",
          f8),
      {"overlaps"});
  check("hole.safetensors", raw_file(R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[4,8]}})", f8),
        {"'a'", "hole"});
  check("trailing.safetensors", raw_file(R"({"a":{"dtype":"F32","shape":[1],"data_offsets":[0,4]}})", f8),
        {"after the last tensor"});
  check("bad_metadata.safetensors", raw_file(R"({"__metadata__":{"seed":7}})", ""), {"__metadata__", "seed"});

  // A real file cut short.
  save_safetensors(dir / "whole.safetensors", {{"a", torch::ones({16})}, {"b", torch::ones({16})}});
  const std::string whole = test::read_file(dir / "whole.safetensors");
  check("cut.safetensors", whole.substr(0, whole.size() - 10), {"'b'", "truncated"});
  check("cut_header.safetensors", whole.substr(0, 20), {"header length"});

  expect_error([&] { SafetensorsFile::open(dir / "absent.safetensors"); },
               {"absent.safetensors", "No such file"});
  const auto file = SafetensorsFile::open(dir / "whole.safetensors");
  expect_error([&] { file.info("c"); }, {"whole.safetensors", "no tensor 'c'"});
  expect_error([&] { file.tensor("c"); }, {"whole.safetensors", "no tensor 'c'"});
}

TEST(Safetensors, BadSavesFailAndLeaveThePreviousFile) {
  test::TempDir dir;
  const auto path = dir / "s.safetensors";
  save_safetensors(path, {{"ok", torch::ones({2})}});
  const std::string before = test::read_file(path);
  expect_error(
      [&] {
        save_safetensors(path, {{"a", torch::ones({1})}, {"a", torch::ones({1})}});
      },
      {"s.safetensors", "'a'", "twice"});
  expect_error(
      [&] {
        save_safetensors(path, {{"__metadata__", torch::ones({1})}});
      },
      {"'__metadata__'", "reserved"});
  expect_error([&] { save_safetensors(path, {{"", torch::ones({1})}}); }, {"empty tensor name"});
  expect_error(
      [&] {
        save_safetensors(path, {{"c", torch::ones({1}, torch::kComplexFloat)}});
      },
      {"'c'", "cannot be stored"});
  expect_error([&] { save_safetensors(path, {{"u", torch::Tensor()}}); }, {"'u'", "undefined"});
  EXPECT_EQ(test::read_file(path), before);
  EXPECT_EQ(std::distance(std::filesystem::directory_iterator(dir.path()), {}), 1);  // no temporaries left
  expect_error(
      [&] {
        save_safetensors(dir / "no_such_dir" / "x.safetensors", {{"a", torch::ones({1})}});
      },
      {"no_such_dir/x.safetensors"});
}

TEST(Safetensors, GoldenFixturesParseAndRewriteIdentically) {
  const auto golden = test::golden_dir();
  ASSERT_TRUE(std::filesystem::is_directory(golden)) << golden << " is missing";
  // Every fixture the README's SHA-256 table lists is here (a missing one fails, naming it), and
  // every .safetensors here is listed.
  const auto readme = golden / "README.md";
  ASSERT_TRUE(std::filesystem::exists(readme)) << readme << " is missing";
  std::set<std::string> listed;
  const std::regex row(R"(\| ([A-Za-z0-9_]+\.(safetensors|json)) \| [0-9a-f]{16} \|)");
  std::istringstream lines(test::read_file(readme));
  for (std::string line; std::getline(lines, line);) {
    std::smatch m;
    if (std::regex_match(line, m, row)) listed.insert(m[1]);
  }
  ASSERT_GE(listed.size(), 10u) << readme << ": the SHA-256 table lists too few fixtures";
  for (const auto& name : listed)
    EXPECT_TRUE(std::filesystem::exists(golden / name))
        << golden / name << " is missing: golden fixtures are never skipped (tests/golden/README.md)";
  int files = 0;
  test::TempDir dir;
  for (const auto& entry : std::filesystem::directory_iterator(golden)) {
    if (entry.path().extension() != ".safetensors") continue;
    SCOPED_TRACE(entry.path().string());
    EXPECT_EQ(listed.count(entry.path().filename().string()), 1u) << "not in " << readme;
    ++files;
    const auto file = SafetensorsFile::open(entry.path());
    EXPECT_FALSE(file.keys().empty());
    EXPECT_FALSE(file.metadata().empty());
    if (file.metadata().count("config") != 0) {
      const auto config = nlohmann::json::parse(file.metadata().at("config"));
      EXPECT_TRUE(config.is_object());
    }
    for (const auto& key : file.keys()) EXPECT_EQ(file.tensor(key).numel(), file.info(key).numel());
    // The Python writer used the same layout rules, so a rewrite reproduces it byte for byte.
    const auto copy = dir / entry.path().filename();
    save_safetensors(copy, file.tensors(), file.metadata());
    EXPECT_EQ(test::read_file(copy), test::read_file(entry.path()));
  }
  EXPECT_GT(files, 0);

  const auto lam = golden / "lam_tiny_weights.safetensors";
  ASSERT_TRUE(std::filesystem::exists(lam))
      << lam << " is missing: golden fixtures are never skipped (tests/golden/README.md)";
  const auto file = SafetensorsFile::open(lam);
  EXPECT_EQ(file.keys().front(), "lam.action_prompt");
  EXPECT_EQ(file.info("lam.encoder.ffn.1.weight").shape, (std::vector<int64_t>{64, 192}));
  EXPECT_EQ(nlohmann::json::parse(file.metadata().at("config"))["model_dim"], 64);
  EXPECT_EQ(file.metadata().at("seed"), "4321");
}

TEST(Safetensors, SavesCudaTensors_CUDA) {
  DOJO_REQUIRE_CUDA();
  test::TempDir dir;
  const auto x = torch::randn({5, 3}, torch::kCUDA).to(torch::kBFloat16).t();
  save_safetensors(dir / "cuda.safetensors", {{"x", x}});
  const auto loaded = SafetensorsFile::open(dir / "cuda.safetensors").tensor("x");
  EXPECT_TRUE(loaded.device().is_cpu());
  EXPECT_TRUE(torch::equal(loaded, x.cpu()));
}

}  // namespace
}  // namespace dojo
