// An append-only journal of finished work items, one JSON object per line, so that a crashed job
// resumes where it stopped (policy evaluation's episodes, planning's). The first line records what
// the job is (`fingerprint`); a journal of another job is refused. A line cut short by a crash is
// skipped with a warning (its item is redone) and the next record starts on a line of its own.
#pragma once

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace dojo {

class JsonJournal {
 public:
  // Opens (creating) `path`; `what` names the job in errors ("policy evaluation"). Throws
  // dojo::Error when the file holds another fingerprint or cannot be appended to.
  JsonJournal(std::filesystem::path path, const nlohmann::json& fingerprint, const std::string& what);
  // The records written so far (by earlier runs too), in order.
  const std::vector<nlohmann::json>& records() const { return records_; }
  // Appends one record and flushes it.
  void append(const nlohmann::json& record);

 private:
  std::filesystem::path path_;
  std::vector<nlohmann::json> records_;
  std::ofstream out_;
};

}  // namespace dojo
