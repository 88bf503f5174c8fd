// A policy in another process, for policy evaluation (eval/policy_eval.h): any language, any
// framework, as long as it speaks the step mode of `dojo serve`'s WebSocket protocol
// (serve/session.h) as a client. The evaluation starts the process with DOJO_POLICY_URL set to a
// loopback ws:// address it listens on and then plays the server's part, whichever world the
// episode runs in (the simulator or the world model): the policy never knows which.
//
// Per episode:
//   policy -> {"type":"start", ...}                     (fields other than the type are ignored)
//   eval   -> {"type":"ready", "mode":"step", "episode":"scene-3", "seed", "width", "height",
//              "actions_per_step", "command": [the start command], "fps"} + the start frame
//   policy -> {"type":"step", "actions": [[raw command] x actions_per_step]}
//   eval   -> the step's frames (binary, DJF1 header + JPEG) + {"type":"step_done", "step",
//              "frames", "done": false}
//   ... until the episode's last step, which is answered by {"type":"step_done", "step",
//       "frames": 0, "done": true} when the next episode begins (or the policy is done); then
//       the policy sends "start" again. The connection closes after its last episode.
// A bad message gets {"type":"error", "message"} and the episode waits for a good one. A
// process that exits, closes the connection or stays silent past the timeout fails the
// evaluation with a one-line error naming the policy (a rerun resumes from the journal).
#pragma once

#include <memory>
#include <string>

#include "eval/policy_eval.h"

namespace dojo::serve {

struct ExternalPolicyOptions {
  std::string name;
  std::string command;     // run by /bin/sh -c, with DOJO_POLICY_URL in its environment
  double timeout_s = 120;  // for the connection and for every answer
  int jpeg_quality = 90;
};

// The process starts at the policy's first episode (reset), which throws dojo::Error naming the
// policy when it does not connect in time or exits first; finish() (or destruction) ends it.
std::unique_ptr<eval::Policy> make_external_policy(const ExternalPolicyOptions& options);

}  // namespace dojo::serve
