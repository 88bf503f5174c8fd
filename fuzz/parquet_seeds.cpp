// Writes the fuzzer's seed corpus: LeRobot-like files from our writer in every codec / page
// version / encoding combination, plus the hyparquet-written test fixture.
#include <cstdio>
#include <fstream>
#include <string>

#include "io/parquet_writer.h"

static const unsigned char kHyparquet[] = {
#include "../tests/io/parquet_fixture_hyparquet.inc"
};

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: parquet_seeds DIR\n");
    return 2;
  }
  const std::string dir = argv[1];
  int count = 0;
  for (auto codec : {dojo::io::ParquetCodec::kUncompressed, dojo::io::ParquetCodec::kSnappy,
                     dojo::io::ParquetCodec::kZstd})
    for (int version : {1, 2})
      for (bool dictionary : {false, true}) {
        dojo::io::ParquetWriteOptions o;
        o.codec = codec;
        o.page_version = version;
        o.dictionary = dictionary;
        o.rows_per_page = 4;
        o.rows_per_row_group = 6;
        dojo::io::ParquetWriter w(o);
        std::vector<int64_t> index;
        std::vector<float> timestamp;
        std::vector<std::string> task;
        std::vector<std::optional<std::vector<float>>> state;
        std::vector<std::optional<double>> reward;
        std::vector<bool> done;
        std::vector<std::vector<std::string>> tasks;
        for (int i = 0; i < 10; ++i) {
          index.push_back(i);
          timestamp.push_back(i * 0.05f);
          task.push_back(i % 2 ? "pick" : "place");
          if (i == 3)
            state.push_back(std::nullopt);
          else
            state.push_back(std::vector<float>{float(i), 0.5f * i});
          if (i % 3 == 1)
            reward.push_back(std::nullopt);
          else
            reward.push_back(i * 0.25);
          done.push_back(i == 9);
          tasks.push_back(std::vector<std::string>(i % 3, "t"));
        }
        w.add_i64("index", index);
        w.add_f32("timestamp", timestamp);
        w.add_string("task", task);
        w.add_list_f32("observation.state", state);
        w.add_optional_f64("next.reward", reward);
        w.add_bool("next.done", done);
        w.add_list_string("tasks", tasks);
        std::ofstream(dir + "/seed_" + std::to_string(count++) + ".parquet", std::ios::binary)
            << w.to_bytes();
      }
  std::ofstream(dir + "/seed_hyparquet.parquet", std::ios::binary)
      .write(reinterpret_cast<const char*>(kHyparquet), sizeof kHyparquet);
  std::printf("%d seeds in %s\n", count + 1, dir.c_str());
  return 0;
}
