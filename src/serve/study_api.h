// The study's HTTP routes (serve/study.h), independent of the transport:
//   POST /api/study/raters              -> {"rater": ID}           a new rater session
//   GET  /api/study/next?rater=ID       -> the rater's next trial: the ground truth and the two
//                                          clips as "left" / "right" (model names withheld),
//                                          the questions, progress; {"done": true} at the end
//   POST /api/study/vote                {"rater", "trial", "answers": {"physics": "left" | "right"
//                                          | "tie", ...}} -> {"stored": true, "remaining": N}
//   GET  /study/clips/PATH              a clip named in study.json (video/mp4)
#pragma once

#include <memory>
#include <string>

#include "serve/rollout_api.h"
#include "serve/study.h"

namespace dojo::serve {

class StudyApi {
 public:
  explicit StudyApi(const std::filesystem::path& dir);  // opens study.json and votes.sqlite
  // Whether `path` is one of the routes above.
  static bool handles(const std::string& path);
  // Answers one request; bad input gets a 4xx whose JSON names the field. Never throws.
  HttpReply handle(const std::string& method, const std::string& path, const std::string& rater_query,
                   const std::string& body, const std::string& user_agent);
  const Study& study() const { return study_; }
  VoteStore& votes() { return *votes_; }

 private:
  HttpReply next(const std::string& rater);
  HttpReply vote(const std::string& body);
  HttpReply clip(const std::string& relative) const;
  size_t answered_in_study(const std::string& rater);

  Study study_;
  std::unique_ptr<VoteStore> votes_;
};

}  // namespace dojo::serve
