// Crash-safe file writes: write to a temporary file in the target's directory, fsync it, rename
// it over the target, fsync the directory. A process killed at any moment leaves either the
// complete old file or the complete new one under the target name (plus, at worst, a stray
// hidden temporary ".NAME.tmp-PID-N" next to it), never a torn mix.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <ostream>
#include <string_view>

namespace dojo {

// Writes `path` atomically; `writer` streams the content. Any failure (the writer throws, the
// disk fills up, the directory is not writable) removes the temporary, leaves `path` as it was
// and throws dojo::Error naming `path` (or rethrows the writer's own exception).
void write_file_atomic(const std::filesystem::path& path, const std::function<void(std::ostream&)>& writer);
void write_file_atomic(const std::filesystem::path& path, std::string_view bytes);

// fsync of a directory, so that renames and creations inside it survive a power loss.
// Throws dojo::Error on failure (a file system that cannot fsync directories is tolerated).
void fsync_directory(const std::filesystem::path& dir);

// --- crash injection, for tests ----------------------------------------------------------------
// Crash-safe code calls crash_point(label) at every step where a crash must be survivable:
// after every write to a temporary file ("atomic:write"), before and after its rename
// ("atomic:before-rename", "atomic:renamed") and between the steps of a checkpoint save (see
// checkpoint.h). With a hook installed, the hook runs there and may kill the process
// (raise(SIGKILL)) to simulate a crash at exactly that point. No hook: nothing happens.
using CrashHook = std::function<void(const char* label)>;
void set_crash_hook(CrashHook hook);
void crash_point(const char* label);

}  // namespace dojo
