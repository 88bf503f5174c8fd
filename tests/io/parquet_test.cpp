// The Parquet reader against (1) a file assembled byte by byte from the Thrift spec, (2) a file
// written by an independent implementation (hyparquet-writer), (3) our writer in every codec /
// page version / encoding combination, and (4) malformed input.
#include "io/parquet.h"

#include <fstream>

#include "core/error.h"
#include "io/parquet_writer.h"
#include "parquet_replay.h"
#include "test_util.h"

namespace dojo::io {
namespace {

// One required INT64 column "x" = [7, -1, 300]: PLAIN, uncompressed, one V1 data page.
// Every byte follows parquet.thrift + the Thrift compact protocol (field header = delta << 4 |
// type; i32/i64 as zigzag varints; lists as size << 4 | element type).
// clang-format off
std::string hand_assembled_file() {
  std::string f = "PAR1";
  const std::vector<uint8_t> page_header = {
      0x15, 0x00,        // 1: type = DATA_PAGE (i32 0)
      0x15, 0x30,        // 2: uncompressed_page_size = 24
      0x15, 0x30,        // 3: compressed_page_size = 24
      0x2c,              // 5: data_page_header (struct, delta 2)
      0x15, 0x06,        //   1: num_values = 3
      0x15, 0x00,        //   2: encoding = PLAIN
      0x15, 0x06,        //   3: definition_level_encoding = RLE
      0x15, 0x06,        //   4: repetition_level_encoding = RLE
      0x00,              //   stop
      0x00};             // stop
  f.append(page_header.begin(), page_header.end());  // 17 bytes at offset 4
  for (int64_t v : {int64_t(7), int64_t(-1), int64_t(300)}) f.append(reinterpret_cast<const char*>(&v), 8);
  const std::vector<uint8_t> footer = {
      0x15, 0x02,                                // 1: version = 1
      0x19, 0x2c,                                // 2: schema, list of 2 structs
      0x48, 0x06, 's', 'c', 'h', 'e', 'm', 'a',  //   root: 4: name = "schema"
      0x15, 0x02, 0x00,                          //         5: num_children = 1; stop
      0x15, 0x04,                                //   x: 1: type = INT64
      0x25, 0x00,                                //      3: repetition_type = REQUIRED
      0x18, 0x01, 'x', 0x00,                     //      4: name = "x"; stop
      0x16, 0x06,                                // 3: num_rows = 3
      0x19, 0x1c,                                // 4: row_groups, list of 1 struct
      0x19, 0x1c,                                //   1: columns, list of 1 struct
      0x26, 0x08,                                //     2: file_offset = 4
      0x1c,                                      //     3: meta_data
      0x15, 0x04,                                //       1: type = INT64
      0x19, 0x15, 0x00,                          //       2: encodings = [PLAIN]
      0x19, 0x18, 0x01, 'x',                     //       3: path_in_schema = ["x"]
      0x15, 0x00,                                //       4: codec = UNCOMPRESSED
      0x16, 0x06,                                //       5: num_values = 3
      0x16, 0x52,                                //       6: total_uncompressed_size = 41
      0x16, 0x52,                                //       7: total_compressed_size = 41
      0x26, 0x08,                                //       9: data_page_offset = 4
      0x00,                                      //       stop (ColumnMetaData)
      0x00,                                      //     stop (ColumnChunk)
      0x16, 0x52,                                //   2: total_byte_size = 41
      0x16, 0x06,                                //   3: num_rows = 3
      0x00,                                      //   stop (RowGroup)
      0x00};                                     // stop (FileMetaData)
  f.append(footer.begin(), footer.end());
  const uint32_t len = static_cast<uint32_t>(footer.size());
  f.append(reinterpret_cast<const char*>(&len), 4);
  return f + "PAR1";
}
// clang-format on

const unsigned char kHyparquetFile[] = {
#include "io/parquet_fixture_hyparquet.inc"
};

// A LeRobot-like table; `rows` rows, lists of 3 floats with one null list and one empty list.
ParquetWriter lerobot_table(const ParquetWriteOptions& options, int rows = 23) {
  ParquetWriter w(options);
  std::vector<int64_t> index;
  std::vector<float> timestamp;
  std::vector<std::string> task;
  std::vector<std::optional<std::vector<float>>> state;
  std::vector<std::optional<double>> reward;
  std::vector<bool> done;
  std::vector<int32_t> small;
  std::vector<std::vector<std::string>> tasks;
  for (int i = 0; i < rows; ++i) {
    index.push_back(int64_t(i) * 1000000007);
    timestamp.push_back(i * 0.05f);
    task.push_back(i % 3 ? "pick up the cup" : "wave");
    if (i == 5)
      state.push_back(std::nullopt);
    else if (i == 6)
      state.push_back(std::vector<float>{});
    else
      state.push_back(std::vector<float>{float(i), -0.5f * i, 1e-3f * i});
    reward.push_back(i % 4 == 1 ? std::nullopt : std::optional<double>(i * 0.25));
    done.push_back(i == rows - 1);
    small.push_back(-i);
    tasks.push_back(std::vector<std::string>(i % 3, "t" + std::to_string(i)));
  }
  w.add_i64("index", index);
  w.add_f32("timestamp", timestamp);
  w.add_string("task", task);
  w.add_list_f32("observation.state", state);
  w.add_optional_f64("next.reward", reward);
  w.add_bool("next.done", done);
  w.add_i32("small", small);
  w.add_list_string("tasks", tasks);
  return w;
}

std::string error_of(const std::function<void()>& fn) { return test::error_message(fn); }

}  // namespace

TEST(Parquet, ReadsHandAssembledFile) {
  const auto f = ParquetFile::from_buffer(hand_assembled_file(), "hand.parquet");
  EXPECT_EQ(f.num_rows(), 3);
  ASSERT_EQ(f.columns().size(), 1u);
  EXPECT_EQ(f.columns()[0].kind, "int64");
  EXPECT_EQ(f.read_i64("x"), (std::vector<int64_t>{7, -1, 300}));
  EXPECT_EQ(f.read_f64("x"), (std::vector<double>{7, -1, 300}));
}

TEST(Parquet, ReadsHyparquetFile) {
  const auto f = ParquetFile::from_buffer(
      std::string(reinterpret_cast<const char*>(kHyparquetFile), sizeof kHyparquetFile), "hyparquet.parquet");
  EXPECT_EQ(f.num_rows(), 6);
  const auto ts = f.read_f32("timestamp");
  const auto frame = f.read_i64("frame_index");
  const auto task = f.read_string("task");
  const auto state = f.read_list_f32("observation.state");
  ASSERT_EQ(state.rows(), 6);
  for (int i = 0; i < 6; ++i) {
    EXPECT_FLOAT_EQ(ts[i], static_cast<float>(i * 0.05));
    EXPECT_EQ(frame[i], i);
    EXPECT_EQ(task[i], i < 4 ? "pick up the cup" : "wave");
    ASSERT_EQ(state.offsets[i + 1] - state.offsets[i], 3);
    EXPECT_FLOAT_EQ(state.values[state.offsets[i]], i);
    EXPECT_FLOAT_EQ(state.values[state.offsets[i] + 1], -i);
    EXPECT_FLOAT_EQ(state.values[state.offsets[i] + 2], i * 0.5f);
  }
}

TEST(Parquet, RoundTripsEveryCodecPageVersionAndEncoding) {
  for (auto codec : {ParquetCodec::kUncompressed, ParquetCodec::kSnappy, ParquetCodec::kZstd})
    for (int version : {1, 2})
      for (bool dictionary : {false, true}) {
        SCOPED_TRACE(testing::Message()
                     << "codec " << int(codec) << " v" << version << " dict " << dictionary);
        ParquetWriteOptions o;
        o.codec = codec;
        o.page_version = version;
        o.dictionary = dictionary;
        o.rows_per_page = 4;       // several pages per chunk
        o.rows_per_row_group = 9;  // several row groups
        const auto f = ParquetFile::from_buffer(lerobot_table(o).to_bytes(), "t.parquet");
        EXPECT_EQ(f.num_rows(), 23);
        EXPECT_EQ(f.num_row_groups(), 3);
        const auto index = f.read_i64("index");
        const auto ts = f.read_f32("timestamp");
        const auto task = f.read_string("task");
        const auto state = f.read_list_f32("observation.state");
        const auto done = f.read_i64("next.done");
        const auto small = f.read_i64("small");
        const auto tasks = f.read_list_string("tasks");
        ASSERT_EQ(state.rows(), 23);
        for (int i = 0; i < 23; ++i) {
          EXPECT_EQ(index[i], int64_t(i) * 1000000007);
          EXPECT_FLOAT_EQ(ts[i], i * 0.05f);
          EXPECT_EQ(task[i], i % 3 ? "pick up the cup" : "wave");
          EXPECT_EQ(done[i], i == 22);
          EXPECT_EQ(small[i], -i);
          const int64_t n = state.offsets[i + 1] - state.offsets[i];
          EXPECT_EQ(n, i == 5 || i == 6 ? 0 : 3) << i;  // null list and empty list read as empty
          if (n == 3) {
            EXPECT_FLOAT_EQ(state.values[state.offsets[i] + 1], -0.5f * i);
            EXPECT_FLOAT_EQ(state.values[state.offsets[i] + 2], 1e-3f * i);
          }
          ASSERT_EQ(tasks.offsets[i + 1] - tasks.offsets[i], i % 3);
          if (i % 3) {
            EXPECT_EQ(tasks.values[tasks.offsets[i]], "t" + std::to_string(i));
          }
        }
      }
}

TEST(Parquet, ColumnKindsAndTypeErrorsNameFileAndColumn) {
  const auto f = ParquetFile::from_buffer(lerobot_table({}).to_bytes(), "data/episode_000007.parquet");
  std::map<std::string, std::string> kinds;
  for (const auto& c : f.columns()) kinds[c.name] = c.kind;
  EXPECT_EQ(kinds["observation.state"], "list<float>");
  EXPECT_EQ(kinds["task"], "string");
  EXPECT_EQ(kinds["small"], "int32");
  EXPECT_EQ(error_of([&] { f.read_string("index"); }),
            "data/episode_000007.parquet: column 'index' is int64, expected string");
  EXPECT_EQ(error_of([&] { f.read_list_f32("timestamp"); }),
            "data/episode_000007.parquet: column 'timestamp' is not a list column");
  EXPECT_EQ(error_of([&] { f.read_f32("observation.state"); }),
            "data/episode_000007.parquet: column 'observation.state' is not a scalar column");
  EXPECT_EQ(error_of([&] { f.read_f64("next.reward"); }),
            "data/episode_000007.parquet: column 'next.reward' is null at row 1");
  EXPECT_EQ(error_of([&] { f.read_f64("nope"); }), "data/episode_000007.parquet: no column 'nope'");
  EXPECT_EQ(error_of([&] { f.read_list_f32("tasks"); }),
            "data/episode_000007.parquet: column 'tasks' is list<string>, expected a list of numbers");
}

TEST(Parquet, TruncatedAndCorruptFilesThrowNamingTheFile) {
  test::TempDir tmp;
  ParquetWriteOptions o;
  o.codec = ParquetCodec::kSnappy;
  o.dictionary = true;
  const std::string good = lerobot_table(o).to_bytes();
  // Cut anywhere: an error naming the file, never a crash.
  for (size_t cut : {size_t(0), size_t(3), size_t(11), good.size() / 3, good.size() / 2, good.size() - 9,
                     good.size() - 1}) {
    const auto path = tmp / "cut.parquet";
    std::ofstream(path, std::ios::binary) << good.substr(0, cut);
    const std::string message = error_of([&] { ParquetFile::open(path).decode_all(); });
    EXPECT_EQ(message.rfind(path.string() + ": ", 0), 0u) << cut << ": " << message;
  }
  // Flipped bytes in the page data: decoded or refused, never undefined behaviour.
  for (size_t at = 4; at < good.size() - 8; at += 7) {
    std::string bad = good;
    bad[at] = static_cast<char>(bad[at] ^ 0x5a);
    try {
      ParquetFile::from_buffer(bad, "flip.parquet").decode_all();
    } catch (const Error& e) {
      EXPECT_EQ(std::string(e.what()).rfind("flip.parquet: ", 0), 0u) << e.what();
    }
  }
  EXPECT_EQ(error_of([&] { ParquetFile::open(tmp / "missing.parquet"); }),
            (tmp / "missing.parquet").string() + ": file not found");
}

TEST(Parquet, LimitsStopHugeAllocations) {
  ParquetLimits limits;
  limits.max_column_values = 10;  // the table has 23 rows
  const auto f = ParquetFile::from_buffer(lerobot_table({}).to_bytes(), "big.parquet", limits);
  EXPECT_NE(error_of([&] { f.read_i64("index"); }).find("value count 23 out of range"), std::string::npos);
}

// Inputs the fuzzer once crashed on (fuzz/regressions/), replayed forever.
// Every committed fuzz input, replayed as the fuzzer runs it: the seed corpus (valid files from
// our writer and hyparquet) must decode completely; the inputs the fuzzer kept for coverage and
// every crasher it found (fixed since) must decode or fail with dojo::Error, nothing worse.
namespace {
std::vector<std::filesystem::path> corpus_files(const std::string& name) {
  std::vector<std::filesystem::path> files;
  const auto dir = std::filesystem::path(DOJO_SOURCE_DIR) / "fuzz" / "corpus" / name;
  if (std::filesystem::is_directory(dir))
    for (const auto& e : std::filesystem::directory_iterator(dir)) files.push_back(e.path());
  return files;
}
}  // namespace

TEST(Parquet, FuzzSeedCorpusDecodes) {
  const auto seeds = corpus_files("seeds");
  ASSERT_GE(seeds.size(), 13u) << "fuzz/corpus/seeds holds the 12 writer combinations and hyparquet's file";
  for (const auto& f : seeds) EXPECT_TRUE(fuzz::replay_parquet_input(test::read_file(f))) << f;
}

TEST(Parquet, FuzzInputsFailCleanly) {
  auto inputs = corpus_files("inputs");
  const auto crashers = corpus_files("crashers");
  inputs.insert(inputs.end(), crashers.begin(), crashers.end());
  ASSERT_FALSE(inputs.empty()) << "fuzz/corpus/inputs is empty";
  int decoded = 0;
  for (const auto& f : inputs) {
    try {
      decoded += fuzz::replay_parquet_input(test::read_file(f)) ? 1 : 0;
    } catch (const std::exception& e) {
      ADD_FAILURE() << f << ": " << e.what();
    }
  }
  // Mostly malformed: at least some inputs must exercise the error paths.
  EXPECT_LT(decoded, static_cast<int>(inputs.size()));
}

}  // namespace dojo::io
