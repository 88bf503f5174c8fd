#include "core/pickle.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>

#include "core/error.h"
#include "test_util.h"

namespace dojo {
namespace {

using Kind = PickleValue::Kind;

// A byte string from a literal that holds NUL bytes.
#define BYTES(literal) std::string(literal, sizeof(literal) - 1)

PickleRef parse(const std::string& bytes, std::set<std::string> globals = {}) {
  PickleOptions options;
  options.source = "test.pkl";
  options.allowed_globals = std::move(globals);
  return read_pickle(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size(), 0, options).value;
}

// The value as the JSON that tests/core/write_torch_files.py writes for the same Python value:
// tuples and sets as lists (sets sorted), bytes as latin-1 text, dict keys as strings.
nlohmann::json to_json(const PickleValue& v) {
  switch (v.kind) {
    case Kind::kNone:
      return nullptr;
    case Kind::kBool:
      return v.boolean;
    case Kind::kInt:
      return v.integer;
    case Kind::kFloat:
      return v.number;
    case Kind::kString:
      return v.text;
    case Kind::kBytes: {
      std::string utf8;  // latin-1 -> UTF-8
      for (const char c : v.text) {
        const auto u = static_cast<uint8_t>(c);
        if (u < 0x80) {
          utf8 += c;
        } else {
          utf8 += static_cast<char>(0xC0 | (u >> 6));
          utf8 += static_cast<char>(0x80 | (u & 0x3F));
        }
      }
      return utf8;
    }
    case Kind::kTuple:
    case Kind::kList:
    case Kind::kSet: {
      nlohmann::json out = nlohmann::json::array();
      for (const auto& item : v.items) out.push_back(to_json(*item));
      if (v.kind == Kind::kSet) std::sort(out.begin(), out.end());
      return out;
    }
    case Kind::kDict: {
      nlohmann::json out = nlohmann::json::object();
      for (const auto& [k, x] : v.entries)
        out[k->kind == Kind::kInt ? std::to_string(k->integer) : k->text] = to_json(*x);
      return out;
    }
    default:
      return "<" + v.describe() + ">";
  }
}

TEST(Pickle, EveryProtocolGivesThePythonValue) {
  const auto dir = test::torch_files_dir();
  const auto expected = nlohmann::json::parse(test::read_file(dir / "values.json"));
  for (int protocol = 0; protocol <= 5; ++protocol) {
    const std::string bytes = test::read_file(dir / ("values_p" + std::to_string(protocol) + ".pkl"));
    ASSERT_FALSE(bytes.empty()) << protocol;
    const auto value = parse(bytes, {"builtins.set", "builtins.frozenset"});
    EXPECT_EQ(to_json(*value), expected) << "protocol " << protocol;
  }
  const auto bytes = parse(test::read_file(dir / "bytes_p4.pkl"));
  EXPECT_EQ(bytes->kind, Kind::kBytes);
  EXPECT_EQ(bytes->text, std::string("\x00\x01"
                                     "abc",
                                     5));
}

TEST(Pickle, RefusesEveryGlobalOutsideTheAllowListAndRunsNothing) {
  // Hand-assembled payloads, one per way a pickle can name a callable.
  const std::vector<std::pair<std::string, std::string>> payloads = {
      {std::string("cos\nsystem\n(S'touch /tmp/dojo_pwned'\ntR."), "os.system"},  // GLOBAL + REDUCE
      {BYTES("\x80\x02"
             "c__builtin__\neval\nX\x03\x00\x00\x00"
             "1+1\x85R."),
       "builtins.eval"},
      {BYTES("\x80\x04\x8c\x0asubprocess\x8c\x05Popen\x93)\x81."), "subprocess.Popen"},  // STACK_GLOBAL
      {std::string("(S'ls'\nios\nsystem\n."), "os.system"},                              // INST
      {std::string("(cposix\nsystem\nS'ls'\no."), "posix.system"},                       // OBJ
  };
  for (const auto& [bytes, global] : payloads) {
    const std::string message = test::error_message([&] { parse(bytes, torch_file_globals()); });
    EXPECT_NE(message.find("refuses global '" + global + "'"), std::string::npos) << message;
    EXPECT_NE(message.find("test.pkl"), std::string::npos) << message;
  }
  // Extension codes name globals indirectly and are refused as such.
  EXPECT_NE(test::error_message([] { parse(BYTES("\x80\x02\x82\x01)R.")); }).find("extension"),
            std::string::npos);
  EXPECT_FALSE(std::filesystem::exists("/tmp/dojo_pwned"));
}

TEST(Pickle, AllowedGlobalsBecomeInertRecords) {
  // torch.Size((2, 3)) and an OrderedDict become plain values; other allowed callables stay records.
  const std::string bytes = BYTES(
      "\x80\x02"
      "ctorch\nSize\nK\x02K\x03\x86\x85R"
      "ccollections\nOrderedDict\n)R"
      "X\x01\x00\x00\x00"
      "aK\x01s"
      "\x86.");
  const auto value = parse(bytes, torch_file_globals());
  ASSERT_EQ(value->kind, Kind::kTuple);
  EXPECT_EQ(to_json(*value->items[0]), nlohmann::json({2, 3}));
  EXPECT_EQ(to_json(*value->items[1]), nlohmann::json({{"a", 1}}));
}

TEST(Pickle, MalformedStreamsFailWithTheirOffset) {
  for (const std::string& bytes : {std::string("\x80\x02]"),
                                   BYTES("\x80\x02X\xff\xff\xff\x7f"
                                         "abc"),
                                   BYTES("\x80\x02h\x05."), std::string("\x80\x02\xff."),
                                   std::string("\x80\x02K\x01K\x02s."), std::string("\x80\x09N.")}) {
    const std::string message = test::error_message([&] { parse(bytes); });
    EXPECT_NE(message.find("test.pkl: pickle byte"), std::string::npos) << message;
  }
}

TEST(Pickle, DeepNestingAndCyclesNeitherCrashNorRecurse) {
  // A million nested lists: building and freeing them must not overflow the stack.
  const size_t depth = 1'000'000;
  std::string bytes = "\x80\x02";
  bytes.append(depth, ']');
  bytes.append(depth - 1, 'a');
  bytes += '.';
  { EXPECT_EQ(parse(bytes)->kind, Kind::kList); }
  // A list that contains itself (through the memo) is refused, and freed (the fuzzer's leak check).
  const std::string message = test::error_message([] {
    parse(
        BYTES("\x80\x04]\x94h\x00"
              "a."));
  });
  EXPECT_NE(message.find("contains itself"), std::string::npos) << message;
  // A cycle among values the result does not reach is freed too; the result stands.
  EXPECT_EQ(parse(BYTES("\x80\x04]\x94h\x00"
                        "a0K\x07."))
                ->integer,
            7);
}

}  // namespace
}  // namespace dojo
