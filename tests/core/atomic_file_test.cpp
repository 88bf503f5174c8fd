// Atomic file writes: content lands whole or not at all, also when the process is SIGKILLed
// in the middle of writing (a forked child kills itself at a chosen crash point).
#include "core/atomic_file.h"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <iterator>

#include "core/error.h"
#include "test_util.h"

namespace dojo {
namespace {

size_t count_entries(const std::filesystem::path& dir) {
  return static_cast<size_t>(std::distance(std::filesystem::directory_iterator(dir), {}));
}

TEST(AtomicFile, WritesContentAndLeavesNoTemporary) {
  test::TempDir dir;
  write_file_atomic(dir / "a.txt", std::string("first"));
  EXPECT_EQ(test::read_file(dir / "a.txt"), "first");
  write_file_atomic(dir / "a.txt", [](std::ostream& out) { out << "second " << 2; });
  EXPECT_EQ(test::read_file(dir / "a.txt"), "second 2");
  EXPECT_EQ(count_entries(dir.path()), 1u);
}

TEST(AtomicFile, LargeStreamedContentIsExact) {
  test::TempDir dir;
  std::string big(5'000'003, '\0');
  for (size_t i = 0; i < big.size(); ++i) big[i] = static_cast<char>(i * 2654435761u >> 13);
  write_file_atomic(dir / "big.bin", [&](std::ostream& out) {
    out.write(big.data(), 17);                                        // through the buffer
    out.write(big.data() + 17, 3'000'000);                            // straight to the file
    for (size_t i = 3'000'017; i < big.size(); ++i) out.put(big[i]);  // byte by byte
  });
  EXPECT_EQ(test::read_file(dir / "big.bin"), big);
}

TEST(AtomicFile, FailingWriterLeavesThePreviousFile) {
  test::TempDir dir;
  write_file_atomic(dir / "a.txt", std::string("keep me"));
  EXPECT_THROW(write_file_atomic(dir / "a.txt",
                                 [](std::ostream& out) {
                                   out << "partial";
                                   throw std::runtime_error("writer failed");
                                 }),
               std::runtime_error);
  EXPECT_EQ(test::read_file(dir / "a.txt"), "keep me");
  EXPECT_EQ(count_entries(dir.path()), 1u);
}

TEST(AtomicFile, UnwritableTargetNamesThePath) {
  test::TempDir dir;
  const std::string message =
      test::error_message([&] { write_file_atomic(dir / "missing_dir" / "a.txt", std::string("x")); });
  EXPECT_NE(message.find("missing_dir/a.txt"), std::string::npos) << message;
}

TEST(AtomicFile, CrashHookSeesEveryStep) {
  test::TempDir dir;
  std::vector<std::string> labels;
  set_crash_hook([&](const char* label) { labels.emplace_back(label); });
  write_file_atomic(dir / "a.bin", std::string(3u << 20, 'x'));  // 3 MiB: several writes
  set_crash_hook(nullptr);
  ASSERT_GE(labels.size(), 4u);
  EXPECT_EQ(labels[0], "atomic:write");
  EXPECT_EQ(labels[labels.size() - 2], "atomic:before-rename");
  EXPECT_EQ(labels.back(), "atomic:renamed");
}

// A child process replaces `path` with `next` and is SIGKILLed at crash point number `kill_at`.
// Returns the child's wait status.
int write_and_die(const std::filesystem::path& path, const std::string& next, int kill_at) {
  return test::run_in_child_killed_at(kill_at, [&] { write_file_atomic(path, next); });
}

TEST(AtomicFile, KilledMidWriteLeavesThePreviousFileIntact) {
  test::TempDir dir;
  const auto path = dir / "weights.bin";
  const std::string old_content(2u << 20, 'o');
  const std::string new_content(5u << 20, 'n');  // 5 writes of 1 MiB, then rename
  write_file_atomic(path, old_content);
  // Count the crash points of one write.
  int points = 0;
  set_crash_hook([&](const char*) { ++points; });
  write_file_atomic(dir / "probe.bin", new_content);
  set_crash_hook(nullptr);
  ASSERT_GE(points, 7);

  for (int kill_at = 0; kill_at < points; ++kill_at) {
    SCOPED_TRACE("killed at crash point " + std::to_string(kill_at));
    write_file_atomic(path, old_content);
    const int status = write_and_die(path, new_content, kill_at);
    ASSERT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL) << status;
    const std::string now = test::read_file(path);
    // Before the rename: the old file, whole. After it: the new one, whole.
    if (kill_at < points - 1) {
      EXPECT_TRUE(now == old_content) << "torn file of " << now.size() << " bytes";
    } else {
      EXPECT_TRUE(now == new_content) << "torn file of " << now.size() << " bytes";
    }
  }
}

}  // namespace
}  // namespace dojo
