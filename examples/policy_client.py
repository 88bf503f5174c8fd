#!/usr/bin/env python3
"""A policy in its own process for `dojo policy eval --external NAME=COMMAND`, standard library only.

    build/dojo policy eval --external "wiggle=python3 examples/policy_client.py --behavior wiggle"

The evaluation starts this process with DOJO_POLICY_URL set and serves the step protocol of
`dojo serve` (docs/policy_eval.md) there, in the simulator and in the world model alike: per
episode, send "start", get "ready" (the start command, actions per step) and the start frame, then
send one step of raw commands at a time and get that step's frames back, until a step_done says
"done": true. The connection closes when the evaluation is over. Replace `decide` with a real
policy: it gets the newest frames (JPEG bytes) and the last command, and returns the next commands.
"""
import argparse, json, math, os, sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from step_client import ConnectionClosed, WorldModelError, WorldModelSession  # noqa: E402


def decide(behavior, frames, last_command, n, t):
    """The next n raw commands. 'hold' keeps the start command; 'wiggle' sways the base joint."""
    rows = []
    for i in range(n):
        row = list(last_command)
        if behavior == "wiggle":
            row[0] = last_command[0] + 0.05 * math.sin((t + i) / 3)
        rows.append(row)
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--url", default=os.environ.get("DOJO_POLICY_URL"), help="default: $DOJO_POLICY_URL")
    p.add_argument("--behavior", choices=["hold", "wiggle"], default="hold")
    p.add_argument("--summary", help="write {episodes, steps, frames} as JSON here at the end")
    a = p.parse_args()
    if not a.url:
        sys.exit("policy_client: no --url and no DOJO_POLICY_URL (run me through dojo policy eval --external)")
    # No read timeout: the evaluation runs other policies before this one's turn comes.
    session = WorldModelSession(a.url, timeout=None)
    episodes, steps, frames = 0, 0, 0
    try:
        while True:
            ready = session.start()  # a closed connection here means the evaluation is over
            episodes += 1
            n, command, t = ready["actions_per_step"], ready["command"], 0
            latest = list(session.start_frames)
            frames += len(latest)
            while True:
                actions = decide(a.behavior, latest, command, n, t)
                latest = session.step(actions)
                steps, frames, t = steps + 1, frames + len(latest), t + n
                command = actions[-1]
                if session.last_step_done.get("done"):
                    break
    except ConnectionClosed:
        pass  # the evaluation is done with this policy
    except (WorldModelError, OSError, ValueError, KeyError) as e:  # an error the evaluation sent, or I/O
        sys.exit(f"policy_client: {type(e).__name__}: {e}")
    if a.summary:
        with open(a.summary, "w") as f:
            json.dump({"episodes": episodes, "steps": steps, "frames": frames}, f)


if __name__ == "__main__":
    main()
