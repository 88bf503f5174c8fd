// The human preference study: raters compare two models' rollouts of the same episode, shown beside
// the ground truth in a random left/right order, on "physics correctness" and "action following"
// (A / B / tie), as in the paper's study.
//
// A study is a directory:
//   study.json      {"format": "dojo-study-1", "name", "models": [...], "questions": [...],
//                    "items": [{"id", "truth": "videos/ID/truth.mp4",
//                               "videos": {"MODEL": "videos/ID/MODEL.mp4", ...}}]}
//   videos/         the clips, paths relative to the directory
//   votes.sqlite    the votes (SQLite in WAL mode, one transaction per vote)
//
// A trial is one item and one pair of models. Every rater sees every trial once, in an order and a
// left/right placement drawn from the rater's id (so the order is fixed per rater and recorded with
// each vote); the page never learns which model is which.
#pragma once

#include <cstdint>
#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

struct sqlite3;

namespace dojo::serve {

struct StudyQuestion {
  std::string id;    // "physics", "action"
  std::string text;  // what the page asks
};

struct StudyItem {
  std::string id;
  std::string truth;                          // relative path of the ground-truth clip
  std::map<std::string, std::string> videos;  // model -> relative path
};

struct StudyTrial {
  std::string id;  // "ITEM|MODEL_A|MODEL_B", the pair in the study's model order
  const StudyItem* item = nullptr;
  std::string model_a, model_b;
};

class Study {
 public:
  // Reads and checks DIR/study.json (every clip it names must exist). Throws dojo::Error naming
  // the file and field.
  static Study open(const std::filesystem::path& dir);
  // Writes DIR/study.json atomically (the clips must already be in DIR).
  void save() const;

  static std::vector<StudyQuestion> default_questions();

  std::filesystem::path dir;
  std::string name;
  std::vector<std::string> models;
  std::vector<StudyQuestion> questions = default_questions();
  std::vector<StudyItem> items;

  // Every (item, model pair), in a fixed order.
  std::vector<StudyTrial> trials() const;
  // The rater's order of the trials, and which model of a trial this rater sees on the left.
  std::vector<StudyTrial> trials_for(const std::string& rater) const;
  std::string left_model(const std::string& rater, const StudyTrial& trial) const;
  // The clip behind a relative path named in study.json; empty when no item names it (so a
  // request can only reach the study's own files).
  std::filesystem::path clip(const std::string& relative) const;
};

// One answer of one rater on one trial.
struct Vote {
  std::string rater, trial, item, model_a, model_b;
  std::string left;      // the model shown on the left
  std::string question;  // a question id
  std::string choice;    // "left" | "right" | "tie"
};

// The votes of a study in SQLite. Thread-safe (one connection behind a mutex). WAL with
// synchronous=FULL: a vote acknowledged to a rater survives the process being killed.
class VoteStore {
 public:
  explicit VoteStore(const std::filesystem::path& file);
  ~VoteStore();
  VoteStore(const VoteStore&) = delete;
  VoteStore& operator=(const VoteStore&) = delete;

  // A new rater session; returns its id (random, 16 hex digits).
  std::string new_rater(const std::string& user_agent);
  bool has_rater(const std::string& rater);
  // All answers of one trial in one transaction. Returns false (and writes nothing) when the
  // rater has already answered this trial.
  bool add(const std::vector<Vote>& answers);
  // Trials this rater has answered.
  std::vector<std::string> answered(const std::string& rater);
  std::vector<Vote> all();

 private:
  void exec(const char* sql);
  std::filesystem::path file_;
  sqlite3* db_ = nullptr;
  std::mutex mutex_;
};

// Win rates per model pair and question, with 95% Wilson score intervals; a tie counts half to
// each side.
struct PairResult {
  std::string model_a, model_b, question;
  int64_t a_wins = 0, b_wins = 0, ties = 0, left_chosen = 0;
  double win_rate_a() const;               // (a_wins + ties / 2) / n
  std::pair<double, double> ci95() const;  // of win_rate_a
  int64_t n() const { return a_wins + b_wins + ties; }
};

struct StudyReport {
  std::string name;
  std::vector<StudyQuestion> questions;
  std::vector<PairResult> pairs;  // every model pair x question, in the study's order
  int64_t raters = 0, votes = 0;
  nlohmann::json to_json() const;
  std::string to_markdown() const;
  std::string to_html() const;
};

StudyReport make_report(const Study& study, const std::vector<Vote>& votes);

// The Wilson score interval of a proportion `p` observed over `n` answers, at z = 1.96.
std::pair<double, double> wilson_interval(double p, int64_t n);

}  // namespace dojo::serve
