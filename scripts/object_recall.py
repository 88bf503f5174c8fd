#!/usr/bin/env python3
"""How much of DojoSim's robot objects a tokenizer keeps, from a `dojo tokenizer eval --video` file.

The robot's objects are saturated red, green or blue cubes and cylinders, a few pixels wide at
64x64. Over the ground-truth pixels of that kind (saturation >= 0.6; red-dominant pixels with much
green, the orange and brown tables, left out), counts those whose reconstruction keeps the hue:
  strict: within 0.3 of the true colour (RGB in [0, 1]) and as saturated;
  hue:    the same dominant channel at saturation > 0.3 (a tinted blob in the right place).
PSNR says little here: the objects are ~1.5 % of the pixels.

  scripts/object_recall.py VIDEO.mp4 SIZE     (SIZE: the clips' height and width, e.g. 64)

Needs ffmpeg/ffprobe and only Python's standard library.
"""
import subprocess
import sys


def probe(path, field):
    return int(subprocess.check_output(["ffprobe", "-v", "error", "-select_streams", "v", "-show_entries",
                                        "stream=" + field, "-of", "csv=p=0", path]))


def object_channel(rgb, min_saturation=0.6):
    hi, lo = max(rgb), min(rgb)
    if hi < 0.25 or (hi - lo) / hi < min_saturation:
        return None
    channel = rgb.index(hi)
    if channel == 0 and rgb[1] > 0.35 * hi:  # orange / brown table
        return None
    return channel


def main():
    path, size = sys.argv[1], int(sys.argv[2])
    width, height = probe(path, "width"), probe(path, "height")
    raw = subprocess.check_output(["ffmpeg", "-v", "error", "-i", path, "-f", "rawvideo", "-pix_fmt", "rgb24", "-"])
    frames = len(raw) // (width * height * 3)
    top = height - 2 * size  # the label strip above the originals; reconstructions below them

    def pixel(f, x, y):
        o = ((f * height + y) * width + x) * 3
        return [raw[o] / 255, raw[o + 1] / 255, raw[o + 2] / 255]

    total = strict = hue = 0
    for f in range(frames):
        for y in range(size):
            for x in range(width):
                truth = pixel(f, x, top + y)
                channel = object_channel(truth)
                if channel is None:
                    continue
                recon = pixel(f, x, top + size + y)
                total += 1
                distance = sum((a - b) ** 2 for a, b in zip(truth, recon)) ** 0.5
                strict += distance < 0.3 and object_channel(recon) == channel
                hi, lo = max(recon), min(recon)
                hue += hi > 0 and (hi - lo) / hi > 0.3 and recon.index(hi) == channel
    print(f"{path}: {total} object pixels in {frames} frames; kept strictly {strict / max(total, 1):.3f}, "
          f"hue kept {hue / max(total, 1):.3f}")


if __name__ == "__main__":
    main()
