#include "core/json_journal.h"

#include "core/error.h"
#include "core/log.h"

namespace fs = std::filesystem;

namespace dojo {

JsonJournal::JsonJournal(fs::path path, const nlohmann::json& fingerprint, const std::string& what)
    : path_(std::move(path)) {
  const bool resuming = fs::exists(path_) && fs::file_size(path_) > 0;
  bool torn = false;
  if (resuming) {
    std::ifstream in(path_);
    std::string line;
    int64_t number = 0;
    while (std::getline(in, line)) {
      ++number;
      if (line.empty()) continue;
      if (number == 1) {
        const auto header = nlohmann::json::parse(line, nullptr, false);
        DOJO_CHECK(!header.is_discarded() && header.contains("fingerprint"),
                   path_.string() + ":1: not a " + what + " journal (no 'fingerprint')");
        DOJO_CHECK(header["fingerprint"] == fingerprint,
                   path_.string() + ": written by another " + what +
                       " (other models, scenes or options); use another output directory or remove it");
        continue;
      }
      const auto record = nlohmann::json::parse(line, nullptr, false);
      if (record.is_discarded() || !record.is_object()) {
        // A line cut short by a crash is the only one that can be bad; its item is redone.
        LOG_WARN(path_.string(), ":", number, ": skipped an unreadable line");
        continue;
      }
      records_.push_back(record);
    }
    std::ifstream tail(path_, std::ios::binary);
    tail.seekg(-1, std::ios::end);
    torn = tail.get() != '\n';
  }
  out_.open(path_, std::ios::app);
  DOJO_CHECK(out_.good(), path_.string() + ": cannot append to the " + what + " journal");
  if (torn) out_ << "\n";
  if (!resuming) out_ << nlohmann::json{{"fingerprint", fingerprint}}.dump() << "\n" << std::flush;
}

void JsonJournal::append(const nlohmann::json& record) {
  out_ << record.dump() << "\n" << std::flush;
  DOJO_CHECK(out_.good(), path_.string() + ": cannot append to the journal");
}

}  // namespace dojo
