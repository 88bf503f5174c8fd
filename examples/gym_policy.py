#!/usr/bin/env python3
"""A LeRobot-style policy on the Gymnasium-style environment of gym_env.py, standard library only.

    build/dojo policy eval --external "sway=python3 examples/gym_policy.py"

LeRobot's policies expose reset() and select_action(observation) -> one action, and are run a step
at a time; `LeRobotStyleAdapter` turns one into what the environment takes (actions_per_step
commands a step) by asking it once per command, as LeRobot's rollout loop does. Replace
`SwayPolicy` with a real one: it gets the newest frames (JPEG bytes) and the command in force.
"""
import argparse, json, math, os, sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from gym_env import DojoStepEnv, EvaluationOver  # noqa: E402
from step_client import WorldModelError  # noqa: E402


class SwayPolicy:
    """select_action: sways the base joint around where it started (0.05 rad, period ~19 commands)."""

    def reset(self):
        self.t, self.home = 0, None

    def select_action(self, observation):
        if self.home is None:
            self.home = list(observation["command"])
        action = list(self.home)
        action[0] = self.home[0] + 0.05 * math.sin(self.t / 3)
        self.t += 1
        return action


class LeRobotStyleAdapter:
    """Runs a select_action policy on DojoStepEnv: actions_per_step calls make one step."""

    def __init__(self, policy):
        self.policy = policy

    def run_episode(self, env):
        observation, info = env.reset()
        self.policy.reset()
        steps, frames = 0, len(observation["frames"])
        while True:
            rows = []
            for _ in range(info["actions_per_step"]):
                rows.append(self.policy.select_action(observation))
                observation = {"frames": observation["frames"], "command": rows[-1]}
            observation, _, terminated, truncated, _ = env.step(rows)
            steps, frames = steps + 1, frames + len(observation["frames"])
            if terminated or truncated:
                return steps, frames


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--url", default=None, help="default: $DOJO_POLICY_URL")
    p.add_argument("--summary", help="write {episodes, steps, frames} as JSON here at the end")
    a = p.parse_args()
    try:
        env = DojoStepEnv(a.url)
    except (ValueError, OSError) as e:
        sys.exit(f"gym_policy: {e}")
    runner = LeRobotStyleAdapter(SwayPolicy())
    episodes = steps = frames = 0
    try:
        while True:
            s, f = runner.run_episode(env)
            episodes, steps, frames = episodes + 1, steps + s, frames + f
    except EvaluationOver:
        pass
    except (WorldModelError, OSError, ValueError, KeyError) as e:  # an error the evaluation sent, or I/O
        sys.exit(f"gym_policy: {type(e).__name__}: {e}")
    if a.summary:
        with open(a.summary, "w") as f:
            json.dump({"episodes": episodes, "steps": steps, "frames": frames}, f)


if __name__ == "__main__":
    main()
