#!/usr/bin/env python3
"""Roll a world model out through `dojo serve` with the standard library only.

    python3 examples/rollout_client.py --server http://127.0.0.1:8080 --image start.jpg --out rollout.mp4

Actions are raw DojoSim arm commands (5 joint targets in radians, gripper opening 0-1); the
server normalises them with the model's range, makes them chunk-relative and places them in the
384-d layout. Without --image the server starts from its dataset's first episode.
"""
import argparse
import base64
import json
import math
import urllib.request


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--server", default="http://127.0.0.1:8080")
    p.add_argument("--token", default="")
    p.add_argument("--model", default="student")
    p.add_argument("--image", help="start frame (JPEG); default: the server's first episode")
    p.add_argument("--steps", type=int, default=12, help="actions to send (a multiple of 4 for the student)")
    p.add_argument("--out", default="rollout.mp4")
    a = p.parse_args()

    # A slow sweep of the base joint with the rest of the arm held: an easy motion to see.
    actions = [[1.0 + 0.4 * math.sin(i / 6), 0.5, 1.8, 0.8, 0.0, 0.5] for i in range(a.steps)]
    body = {"model": a.model, "actions": actions, "format": "mp4", "seed": 0}
    if a.image:
        with open(a.image, "rb") as f:
            body["image"] = base64.b64encode(f.read()).decode()
    headers = {"Content-Type": "application/json"}
    if a.token:
        headers["Authorization"] = "Bearer " + a.token
    request = urllib.request.Request(a.server + "/v1/rollout", json.dumps(body).encode(), headers)
    try:
        with urllib.request.urlopen(request) as reply, open(a.out, "wb") as out:
            out.write(reply.read())
    except urllib.error.HTTPError as e:
        raise SystemExit(f"server: {e.code} {e.read().decode()}")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
