#include "serve/study.h"

#include <sqlite3.h>

#include <algorithm>
#include <cmath>
#include <iomanip>
#include <random>
#include <set>
#include <sstream>

#include "core/atomic_file.h"
#include "core/error.h"
#include "core/json_file.h"
#include "core/stable_hash.h"

namespace dojo::serve {

namespace fs = std::filesystem;

namespace {

constexpr const char* kFormat = "dojo-study-1";

bool safe_relative(const std::string& path) {
  if (path.empty() || path.front() == '/' || path.find('\\') != std::string::npos) return false;
  for (const auto& part : fs::path(path))
    if (part == ".." || part == ".") return false;
  return true;
}

std::string string_field(const nlohmann::json& j, const char* key, const std::string& where) {
  DOJO_CHECK(j.contains(key) && j[key].is_string() && !j[key].get<std::string>().empty(),
             where + ": '" + key + "' must be a non-empty string");
  return j[key].get<std::string>();
}

std::string percent(double x) {
  std::ostringstream s;
  s << std::fixed << std::setprecision(1) << 100 * x << "%";
  return s.str();
}

std::string html_escape(const std::string& text) {
  std::string out;
  for (const char c : text) {
    if (c == '<')
      out += "&lt;";
    else if (c == '>')
      out += "&gt;";
    else if (c == '&')
      out += "&amp;";
    else if (c == '"')
      out += "&quot;";
    else
      out += c;
  }
  return out;
}

}  // namespace

// --- the study ---------------------------------------------------------------------------------

std::vector<StudyQuestion> Study::default_questions() {
  return {{"physics", "Which video shows more correct physics (objects, contacts, the arm's body)?"},
          {"action", "Which video follows the actions of the ground truth better?"}};
}

Study Study::open(const fs::path& dir) {
  const auto file = dir / "study.json";
  const auto j = read_json_file(file);
  const auto where = file.string();
  DOJO_CHECK(j.is_object() && j.contains("format") && j["format"].is_string() && j["format"] == kFormat,
             where + ": 'format' must be \"" + std::string(kFormat) + "\"");
  DOJO_CHECK(!j.contains("name") || j["name"].is_string(), where + ": 'name' must be a string");
  Study s;
  s.dir = dir;
  s.name = j.value("name", dir.filename().string());
  DOJO_CHECK(j.contains("models") && j["models"].is_array() && j["models"].size() >= 2,
             where + ": 'models' must list at least two models");
  for (const auto& m : j["models"]) {
    DOJO_CHECK(
        m.is_string() && !m.get<std::string>().empty() && m.get<std::string>().find('|') == std::string::npos,
        where + ": 'models' must be non-empty names without '|'");
    s.models.push_back(m.get<std::string>());
  }
  DOJO_CHECK(std::set<std::string>(s.models.begin(), s.models.end()).size() == s.models.size(),
             where + ": 'models' has a name twice");
  if (j.contains("questions")) {
    DOJO_CHECK(j["questions"].is_array() && !j["questions"].empty(),
               where + ": 'questions' must be a non-empty array");
    s.questions.clear();
    std::set<std::string> question_ids;
    for (size_t i = 0; i < j["questions"].size(); ++i) {
      const auto at = where + " questions[" + std::to_string(i) + "]";
      const auto& q = j["questions"][i];
      s.questions.push_back({string_field(q, "id", at), string_field(q, "text", at)});
      DOJO_CHECK(question_ids.insert(s.questions.back().id).second,
                 at + ": id '" + s.questions.back().id + "' twice");
    }
  }
  DOJO_CHECK(j.contains("items") && j["items"].is_array() && !j["items"].empty(),
             where + ": 'items' must be a non-empty array");
  std::set<std::string> ids;
  for (size_t index = 0; index < j["items"].size(); ++index) {
    const auto& it = j["items"][index];
    StudyItem item;
    item.id = string_field(it, "id", where + " items[" + std::to_string(index) + "]");
    const auto at = where + " item '" + item.id + "'";
    DOJO_CHECK(item.id.find('|') == std::string::npos && ids.insert(item.id).second,
               at + ": ids must be unique and contain no '|'");
    item.truth = string_field(it, "truth", at);
    DOJO_CHECK(it.contains("videos") && it["videos"].is_object(), at + ": 'videos' must be an object");
    for (const auto& model : s.models)
      item.videos[model] = string_field(it["videos"], model.c_str(), at + " videos");
    for (const auto* path : {&item.truth})
      DOJO_CHECK(safe_relative(*path), at + ": '" + *path + "' must be a relative path inside the study");
    for (const auto& [model, path] : item.videos) {
      DOJO_CHECK(safe_relative(path), at + ": '" + path + "' must be a relative path inside the study");
      DOJO_CHECK(fs::is_regular_file(dir / path), at + ": missing clip " + (dir / path).string());
    }
    DOJO_CHECK(fs::is_regular_file(dir / item.truth), at + ": missing clip " + (dir / item.truth).string());
    s.items.push_back(std::move(item));
  }
  return s;
}

void Study::save() const {
  nlohmann::json items_json = nlohmann::json::array();
  for (const auto& item : items)
    items_json.push_back({{"id", item.id}, {"truth", item.truth}, {"videos", item.videos}});
  nlohmann::json questions_json = nlohmann::json::array();
  for (const auto& q : questions) questions_json.push_back({{"id", q.id}, {"text", q.text}});
  const nlohmann::json j = {{"format", kFormat},
                            {"name", name},
                            {"models", models},
                            {"questions", questions_json},
                            {"items", items_json}};
  write_file_atomic(dir / "study.json", j.dump(2) + "\n");
}

std::vector<StudyTrial> Study::trials() const {
  std::vector<StudyTrial> out;
  for (const auto& item : items)
    for (size_t a = 0; a < models.size(); ++a)
      for (size_t b = a + 1; b < models.size(); ++b)
        out.push_back({item.id + "|" + models[a] + "|" + models[b], &item, models[a], models[b]});
  return out;
}

std::vector<StudyTrial> Study::trials_for(const std::string& rater) const {
  auto out = trials();
  std::mt19937_64 rng(stable_hash("order|" + rater));
  std::shuffle(out.begin(), out.end(), rng);
  return out;
}

std::string Study::left_model(const std::string& rater, const StudyTrial& trial) const {
  return stable_hash("side|" + rater + "|" + trial.id) & 1 ? trial.model_b : trial.model_a;
}

fs::path Study::clip(const std::string& relative) const {
  for (const auto& item : items) {
    if (item.truth == relative) return dir / relative;
    for (const auto& [model, path] : item.videos)
      if (path == relative) return dir / relative;
  }
  return {};
}

// --- votes -------------------------------------------------------------------------------------

VoteStore::VoteStore(const fs::path& file) : file_(file) {
  const int rc = sqlite3_open_v2(file.c_str(), &db_,
                                 SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX, nullptr);
  if (rc != SQLITE_OK) {
    const std::string message = db_ ? sqlite3_errmsg(db_) : "out of memory";
    sqlite3_close(db_);
    db_ = nullptr;
    throw Error(file.string() + ": cannot open the vote database: " + message);
  }
  sqlite3_busy_timeout(db_, 10000);  // another process (a report) may hold the lock briefly
  try {
    exec("PRAGMA journal_mode=WAL");
    exec("PRAGMA synchronous=FULL");
    exec(
        "CREATE TABLE IF NOT EXISTS raters(id TEXT PRIMARY KEY, created_at TEXT NOT NULL, "
        "user_agent TEXT);"
        "CREATE TABLE IF NOT EXISTS votes(rater TEXT NOT NULL, trial TEXT NOT NULL, item TEXT NOT NULL, "
        "model_a TEXT NOT NULL, model_b TEXT NOT NULL, left_model TEXT NOT NULL, question TEXT NOT NULL, "
        "choice TEXT NOT NULL CHECK(choice IN ('left','right','tie')), created_at TEXT NOT NULL, "
        "PRIMARY KEY(rater, trial, question));");
  } catch (...) {  // the destructor does not run for a constructor that throws
    sqlite3_close(db_);
    db_ = nullptr;
    throw;
  }
}

VoteStore::~VoteStore() {
  if (db_) sqlite3_close(db_);
}

void VoteStore::exec(const char* sql) {
  char* message = nullptr;
  if (sqlite3_exec(db_, sql, nullptr, nullptr, &message) != SQLITE_OK) {
    const std::string text = message ? message : "unknown error";
    sqlite3_free(message);
    throw Error(file_.string() + ": " + text);
  }
}

namespace {

// A prepared statement that finalises itself.
class Statement {
 public:
  Statement(sqlite3* db, const char* sql, const fs::path& file) : file_(file) {
    if (sqlite3_prepare_v2(db, sql, -1, &stmt_, nullptr) != SQLITE_OK)
      throw Error(file.string() + ": " + sqlite3_errmsg(db));
  }
  ~Statement() { sqlite3_finalize(stmt_); }
  Statement& bind(int index, const std::string& text) {
    sqlite3_bind_text(stmt_, index, text.c_str(), static_cast<int>(text.size()), SQLITE_TRANSIENT);
    return *this;
  }
  int step() { return sqlite3_step(stmt_); }
  void reset() {
    sqlite3_reset(stmt_);
    sqlite3_clear_bindings(stmt_);
  }
  std::string column(int index) {
    const auto* text = sqlite3_column_text(stmt_, index);
    return text ? reinterpret_cast<const char*>(text) : "";
  }

 private:
  sqlite3_stmt* stmt_ = nullptr;
  fs::path file_;
};

}  // namespace

std::string VoteStore::new_rater(const std::string& user_agent) {
  std::random_device entropy;
  std::ostringstream id;
  id << std::hex << std::setfill('0') << std::setw(8) << entropy() << std::setw(8) << entropy();
  std::lock_guard<std::mutex> lock(mutex_);
  Statement insert(db_, "INSERT INTO raters(id, created_at, user_agent) VALUES(?, datetime('now'), ?)",
                   file_);
  insert.bind(1, id.str()).bind(2, user_agent.substr(0, 256));
  DOJO_CHECK(insert.step() == SQLITE_DONE, file_.string() + ": cannot add a rater: " + sqlite3_errmsg(db_));
  return id.str();
}

bool VoteStore::has_rater(const std::string& rater) {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement query(db_, "SELECT 1 FROM raters WHERE id = ?", file_);
  query.bind(1, rater);
  return query.step() == SQLITE_ROW;
}

bool VoteStore::add(const std::vector<Vote>& answers) {
  DOJO_CHECK(!answers.empty(), "a vote needs at least one answer");
  std::lock_guard<std::mutex> lock(mutex_);
  exec("BEGIN IMMEDIATE");
  try {
    Statement seen(db_, "SELECT 1 FROM votes WHERE rater = ? AND trial = ? LIMIT 1", file_);
    seen.bind(1, answers.front().rater).bind(2, answers.front().trial);
    if (seen.step() == SQLITE_ROW) {
      exec("ROLLBACK");
      return false;
    }
    Statement insert(db_,
                     "INSERT INTO votes(rater, trial, item, model_a, model_b, left_model, question, choice, "
                     "created_at) VALUES(?, ?, ?, ?, ?, ?, ?, ?, datetime('now'))",
                     file_);
    for (const auto& v : answers) {
      insert.bind(1, v.rater).bind(2, v.trial).bind(3, v.item).bind(4, v.model_a).bind(5, v.model_b);
      insert.bind(6, v.left).bind(7, v.question).bind(8, v.choice);
      DOJO_CHECK(insert.step() == SQLITE_DONE,
                 file_.string() + ": cannot store a vote: " + sqlite3_errmsg(db_));
      insert.reset();
    }
    exec("COMMIT");  // synchronous=FULL: on disk before the rater hears "stored"
    return true;
  } catch (...) {
    sqlite3_exec(db_, "ROLLBACK", nullptr, nullptr, nullptr);
    throw;
  }
}

std::vector<std::string> VoteStore::answered(const std::string& rater) {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement query(db_, "SELECT DISTINCT trial FROM votes WHERE rater = ?", file_);
  query.bind(1, rater);
  std::vector<std::string> out;
  while (query.step() == SQLITE_ROW) out.push_back(query.column(0));
  return out;
}

std::vector<Vote> VoteStore::all() {
  std::lock_guard<std::mutex> lock(mutex_);
  Statement query(db_,
                  "SELECT rater, trial, item, model_a, model_b, left_model, question, choice FROM votes "
                  "ORDER BY rowid",
                  file_);
  std::vector<Vote> out;
  while (query.step() == SQLITE_ROW)
    out.push_back({query.column(0), query.column(1), query.column(2), query.column(3), query.column(4),
                   query.column(5), query.column(6), query.column(7)});
  return out;
}

// --- the report --------------------------------------------------------------------------------

std::pair<double, double> wilson_interval(double p, int64_t n) {
  if (n <= 0) return {0.0, 1.0};
  constexpr double z = 1.959963984540054;
  const double z2n = z * z / n;
  const double centre = (p + z2n / 2) / (1 + z2n);
  const double half = z * std::sqrt(p * (1 - p) / n + z2n / (4 * n)) / (1 + z2n);
  return {std::max(0.0, centre - half), std::min(1.0, centre + half)};
}

double PairResult::win_rate_a() const { return n() ? (a_wins + 0.5 * ties) / n() : 0.0; }

std::pair<double, double> PairResult::ci95() const { return wilson_interval(win_rate_a(), n()); }

StudyReport make_report(const Study& study, const std::vector<Vote>& votes) {
  StudyReport r;
  r.name = study.name;
  r.questions = study.questions;
  std::set<std::string> raters;
  for (size_t a = 0; a < study.models.size(); ++a)
    for (size_t b = a + 1; b < study.models.size(); ++b)
      for (const auto& q : study.questions) r.pairs.push_back({study.models[a], study.models[b], q.id});
  for (const auto& v : votes) {
    auto it = std::find_if(r.pairs.begin(), r.pairs.end(), [&](const PairResult& p) {
      return p.model_a == v.model_a && p.model_b == v.model_b && p.question == v.question;
    });
    if (it == r.pairs.end()) continue;  // a model or question no longer in study.json
    raters.insert(v.rater);
    ++r.votes;
    if (v.choice == "tie") {
      ++it->ties;
      continue;
    }
    if (v.choice == "left") ++it->left_chosen;
    const auto& winner = v.choice == "left" ? v.left : (v.left == v.model_a ? v.model_b : v.model_a);
    ++(winner == v.model_a ? it->a_wins : it->b_wins);
  }
  r.raters = static_cast<int64_t>(raters.size());
  return r;
}

nlohmann::json StudyReport::to_json() const {
  nlohmann::json pairs_json = nlohmann::json::array();
  for (const auto& p : pairs) {
    const auto [low, high] = p.ci95();
    pairs_json.push_back({{"model_a", p.model_a},
                          {"model_b", p.model_b},
                          {"question", p.question},
                          {"a_wins", p.a_wins},
                          {"b_wins", p.b_wins},
                          {"ties", p.ties},
                          {"n", p.n()},
                          {"win_rate_a", p.win_rate_a()},
                          {"ci95", {low, high}},
                          {"left_chosen", p.left_chosen}});
  }
  nlohmann::json questions_json = nlohmann::json::array();
  for (const auto& q : questions) questions_json.push_back({{"id", q.id}, {"text", q.text}});
  return {{"name", name},
          {"raters", raters},
          {"votes", votes},
          {"questions", questions_json},
          {"pairs", pairs_json},
          {"method",
           "win rate of model_a over model_b, a tie counting half; 95% Wilson score interval over n answers, "
           "which treats answers as independent (one rater's answers are not: with few raters giving many "
           "answers the interval is too narrow)"}};
}

namespace {

// The paper's layout: a column per model pair ("A > B"), a row per question.
std::vector<std::pair<std::string, std::string>> pair_columns(const std::vector<PairResult>& pairs) {
  std::vector<std::pair<std::string, std::string>> out;
  for (const auto& p : pairs)
    if (std::find(out.begin(), out.end(), std::make_pair(p.model_a, p.model_b)) == out.end())
      out.emplace_back(p.model_a, p.model_b);
  return out;
}

const PairResult& cell(const std::vector<PairResult>& pairs,
                       const std::pair<std::string, std::string>& column, const std::string& question) {
  return *std::find_if(pairs.begin(), pairs.end(), [&](const PairResult& p) {
    return p.model_a == column.first && p.model_b == column.second && p.question == question;
  });
}

std::string cell_text(const PairResult& p) {
  if (p.n() == 0) return "no votes";
  const auto [low, high] = p.ci95();
  return percent(p.win_rate_a()) + " [" + percent(low) + ", " + percent(high) +
         "] (n=" + std::to_string(p.n()) + ")";
}

}  // namespace

std::string StudyReport::to_markdown() const {
  const auto columns = pair_columns(pairs);
  std::ostringstream md;
  md << "# Preference study: " << name << "\n\n"
     << raters << " raters, " << votes
     << " answers. Win rate of the first model over the second (a tie counts "
     << "half), with its 95% Wilson interval and the number of answers.\n\n|  |";
  for (const auto& c : columns) md << " " << c.first << " > " << c.second << " |";
  md << "\n|---|";
  for (size_t i = 0; i < columns.size(); ++i) md << "---|";
  md << "\n";
  for (const auto& q : questions) {
    md << "| " << q.id << " |";
    for (const auto& c : columns) md << " " << cell_text(cell(pairs, c, q.id)) << " |";
    md << "\n";
  }
  return md.str();
}

std::string StudyReport::to_html() const {
  const auto columns = pair_columns(pairs);
  std::ostringstream h;
  h << "<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>Preference study: "
    << html_escape(name)
    << "</title><style>body{font:14px system-ui,sans-serif;margin:1.5em}table{border-collapse:collapse}"
       "td,th{border:1px solid #ccc;padding:.3em .7em;text-align:left}"
       ".bar{display:inline-block;height:.6em;background:#4a7;vertical-align:middle;margin-right:.4em}"
       "</style></head><body><h2>Preference study: "
    << html_escape(name) << "</h2><p>" << raters << " raters, " << votes
    << " answers. Win rate of the first model over the second (a tie counts half), 95% Wilson interval, "
       "answers.</p><table><tr><th></th>";
  for (const auto& c : columns)
    h << "<th>" << html_escape(c.first) << " &gt; " << html_escape(c.second) << "</th>";
  h << "</tr>";
  for (const auto& q : questions) {
    h << "<tr><th title=\"" << html_escape(q.text) << "\">" << html_escape(q.id) << "</th>";
    for (const auto& c : columns) {
      const auto& p = cell(pairs, c, q.id);
      h << "<td><span class=\"bar\" style=\"width:" << static_cast<int>(60 * p.win_rate_a()) << "px\"></span>"
        << html_escape(cell_text(p)) << "</td>";
    }
    h << "</tr>";
  }
  h << "</table></body></html>\n";
  return h.str();
}

}  // namespace dojo::serve
