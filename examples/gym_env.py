#!/usr/bin/env python3
"""A Gymnasium-style environment over the step protocol, standard library only.

The environment is DojoSim or a world model, whichever `dojo policy eval --external` (or a
`dojo serve` step session) puts behind the connection; the policy never learns which:

    env = DojoStepEnv()                     # connects to $DOJO_POLICY_URL
    observation, info = env.reset()         # waits for the evaluation's next episode
    while True:
        observation, reward, terminated, truncated, info = env.step(actions)
        if terminated or truncated:
            break

An observation is {"frames": [JPEG bytes, ...] (those shown since the last step, the newest last),
"command": [the command in force]}; an action is `actions_per_step` rows of raw commands (the
robot's 6 values). The reward is 0: success is scored by the evaluation, not told to the policy.
`reset()` raises EvaluationOver when the evaluation has no episode left for this policy.

`examples/gym_policy.py` runs a LeRobot-style policy (select_action on an observation) on it.
"""
import os, sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from step_client import ConnectionClosed, WorldModelSession  # noqa: E402


class EvaluationOver(Exception):
    """No episode is left for this policy."""


class DojoStepEnv:
    """reset() / step() over one step-protocol connection (Gymnasium's five-tuple)."""

    def __init__(self, url=None, timeout=None):
        url = url or os.environ.get("DOJO_POLICY_URL")
        if not url:
            raise ValueError("no url and no DOJO_POLICY_URL (run through dojo policy eval --external)")
        # No read timeout by default: the evaluation runs other policies before this one's turn.
        self.session = WorldModelSession(url, timeout=timeout)
        self.actions_per_step, self.command, self.episode = 0, None, None

    def reset(self, seed=None, options=None):
        try:
            ready = self.session.start()
        except ConnectionClosed as e:
            raise EvaluationOver() from e
        self.actions_per_step, self.command = ready["actions_per_step"], list(ready["command"])
        self.episode = ready.get("episode")
        observation = {"frames": [f["jpeg"] for f in self.session.start_frames], "command": self.command}
        return observation, {"episode": self.episode, "actions_per_step": self.actions_per_step,
                             "fps": ready.get("fps")}

    def step(self, actions):
        if len(actions) != self.actions_per_step:
            raise ValueError(f"expected {self.actions_per_step} rows of commands, got {len(actions)}")
        frames = self.session.step([list(map(float, row)) for row in actions])
        self.command = list(actions[-1])
        done = bool(self.session.last_step_done.get("done"))
        observation = {"frames": [f["jpeg"] for f in frames], "command": self.command}
        return observation, 0.0, done, False, {"step": self.session.last_step_done.get("step")}

    def close(self):
        self.session.close()
