#include "serve/study_api.h"

#include <algorithm>
#include <fstream>
#include <set>
#include <sstream>

#include "core/error.h"

namespace dojo::serve {

namespace {

constexpr const char* kClipPrefix = "/study/clips/";

HttpReply json_reply(int status, const nlohmann::json& body) {
  return {status, "application/json", body.dump()};
}
HttpReply error_reply(int status, const std::string& message) {
  return json_reply(status, {{"error", message}});
}

}  // namespace

StudyApi::StudyApi(const std::filesystem::path& dir)
    : study_(Study::open(dir)), votes_(std::make_unique<VoteStore>(dir / "votes.sqlite")) {}

bool StudyApi::handles(const std::string& path) {
  return path.rfind("/api/study/", 0) == 0 || path.rfind(kClipPrefix, 0) == 0;
}

HttpReply StudyApi::handle(const std::string& method, const std::string& path, const std::string& rater_query,
                           const std::string& body, const std::string& user_agent) {
  try {
    if (path == "/api/study/raters") {
      if (method != "POST") return error_reply(405, "use POST");
      return json_reply(200, {{"rater", votes_->new_rater(user_agent)}, {"study", study_.name}});
    }
    if (path == "/api/study/next") {
      if (method != "GET") return error_reply(405, "use GET");
      return next(rater_query);
    }
    if (path == "/api/study/vote") {
      if (method != "POST") return error_reply(405, "use POST");
      return vote(body);
    }
    if (path.rfind(kClipPrefix, 0) == 0 && method == "GET")
      return clip(path.substr(std::string(kClipPrefix).size()));
    return error_reply(404, "no route " + path);
  } catch (const std::exception& e) {
    return error_reply(500, e.what());
  }
}

HttpReply StudyApi::next(const std::string& rater) {
  if (rater.empty() || !votes_->has_rater(rater))
    return error_reply(400, "'rater': unknown rater; POST /api/study/raters first");
  const auto done = votes_->answered(rater);
  const std::set<std::string> answered(done.begin(), done.end());
  const auto trials = study_.trials_for(rater);
  const auto it =
      std::find_if(trials.begin(), trials.end(), [&](const StudyTrial& t) { return !answered.count(t.id); });
  nlohmann::json progress = {{"answered", answered_in_study(rater)}, {"total", trials.size()}};
  if (it == trials.end()) return json_reply(200, {{"done", true}, {"progress", progress}});
  const auto left = study_.left_model(rater, *it);
  const auto right = left == it->model_a ? it->model_b : it->model_a;
  nlohmann::json questions = nlohmann::json::array();
  for (const auto& q : study_.questions) questions.push_back({{"id", q.id}, {"text", q.text}});
  return json_reply(200, {{"done", false},
                          {"trial", it->id},
                          {"truth", kClipPrefix + it->item->truth},
                          {"left", kClipPrefix + it->item->videos.at(left)},
                          {"right", kClipPrefix + it->item->videos.at(right)},
                          {"questions", questions},
                          {"progress", progress}});
}

size_t StudyApi::answered_in_study(const std::string& rater) {
  // Votes on trials no longer in study.json (a model or item removed) do not count.
  const auto done = votes_->answered(rater);
  const std::set<std::string> answered(done.begin(), done.end());
  size_t n = 0;
  for (const auto& t : study_.trials()) n += answered.count(t.id);
  return n;
}

HttpReply StudyApi::vote(const std::string& body) {
  const auto request = nlohmann::json::parse(body, nullptr, /*allow_exceptions=*/false);
  if (request.is_discarded() || !request.is_object())
    return error_reply(400, "vote: the body must be a JSON object");
  for (const char* key : {"rater", "trial"})
    if (!request.contains(key) || !request[key].is_string())
      return error_reply(400, std::string("vote: '") + key + "' must be a string");
  const auto rater = request["rater"].get<std::string>();
  const auto trial_id = request["trial"].get<std::string>();
  if (!votes_->has_rater(rater)) return error_reply(400, "vote: 'rater': unknown rater");
  const auto trials = study_.trials();
  const auto trial =
      std::find_if(trials.begin(), trials.end(), [&](const StudyTrial& t) { return t.id == trial_id; });
  if (trial == trials.end())
    return error_reply(400, "vote: 'trial': no trial '" + trial_id + "' in this study");
  if (!request.contains("answers") || !request["answers"].is_object())
    return error_reply(400, "vote: 'answers' must be an object with one answer per question");
  std::vector<Vote> answers;
  const auto left = study_.left_model(rater, *trial);  // the placement this rater was shown
  for (const auto& q : study_.questions) {
    const auto& a = request["answers"];
    if (!a.contains(q.id) || !a[q.id].is_string())
      return error_reply(400, "vote: 'answers." + q.id + "' must be \"left\", \"right\" or \"tie\"");
    const auto choice = a[q.id].get<std::string>();
    if (choice != "left" && choice != "right" && choice != "tie")
      return error_reply(400, "vote: 'answers." + q.id + "' must be \"left\", \"right\" or \"tie\"");
    answers.push_back(
        {rater, trial->id, trial->item->id, trial->model_a, trial->model_b, left, q.id, choice});
  }
  if (request["answers"].size() != study_.questions.size())
    return error_reply(400, "vote: 'answers' has a question this study does not ask");
  if (!votes_->add(answers))
    return error_reply(409, "vote: this rater has already answered trial '" + trial_id + "'");
  return json_reply(200, {{"stored", true}, {"remaining", trials.size() - answered_in_study(rater)}});
}

HttpReply StudyApi::clip(const std::string& relative) const {
  const auto file = study_.clip(relative);
  if (file.empty()) return error_reply(404, "no clip '" + relative + "' in this study");
  std::ifstream in(file, std::ios::binary);
  if (!in) return error_reply(404, file.string() + ": cannot read");
  std::ostringstream bytes;
  bytes << in.rdbuf();
  return {200, "video/mp4", bytes.str()};
}

}  // namespace dojo::serve
