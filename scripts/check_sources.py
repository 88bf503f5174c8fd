#!/usr/bin/env python3
"""Source checks CI runs before building (standard library only):

  layers   each layer's dojo_layer(...) DEPS in CMakeLists.txt name exactly the layers its files
           include ("core/...", "io/...": the directory of src/ an include names), so a link line
           never carries a layer nobody uses nor relies on one arriving through another
  format   every tracked .cpp/.h is clang-formatted (.clang-format), when clang-format is installed

Exits 1 naming each file or layer that fails.
"""
import pathlib
import re
import shutil
import subprocess
import sys

root = pathlib.Path(__file__).resolve().parent.parent
failures = []

# --- layers ---------------------------------------------------------------------------------
cmake = (root / "CMakeLists.txt").read_text()
declared = {}
for match in re.finditer(r"^\s*dojo_layer\((\w+)([^)]*)\)", cmake, re.M):
    name, rest = match.group(1), match.group(2)
    if "SOURCES" in rest:
        continue  # the engine-only build's partial layers
    deps = re.search(r"\bDEPS\b(.*?)(?:\bLIBS\b|\bEXCLUDE\b|$)", rest, re.S)
    words = deps.group(1).split() if deps else []
    declared[name] = set(w.replace("${DOJO_SIM_LAYER}", "sim") for w in words)
for name, deps in sorted(declared.items()):
    used = set()
    for f in sorted((root / "src" / name).glob("*.[ch]*")):
        for inc in re.findall(r'^#include "(\w+)/', f.read_text(), re.M):
            used.add(inc)
    used.discard(name)
    if used != deps:
        extra, missing = sorted(deps - used), sorted(used - deps)
        failures.append(f"CMakeLists.txt: dojo_layer({name}) DEPS" +
                        (f" list {', '.join(extra)} that src/{name} never includes" if extra else "") +
                        (";" if extra and missing else "") +
                        (f" lack {', '.join(missing)} that src/{name} includes" if missing else ""))

# --- format ---------------------------------------------------------------------------------
formatter = shutil.which("clang-format")
if formatter:
    files = subprocess.run(["git", "ls-files", "*.cpp", "*.h"], cwd=root, capture_output=True, text=True,
                           check=True).stdout.split()
    for f in files:
        r = subprocess.run([formatter, "--dry-run", "--Werror", f], cwd=root, capture_output=True, text=True)
        if r.returncode != 0:
            failures.append(f"{f}: not clang-formatted (run: clang-format -i {f})")
else:
    print("[check] clang-format not installed: formatting not checked", file=sys.stderr)

for f in failures:
    print(f, file=sys.stderr)
print(f"[check] {len(declared)} layers, {'formatting' if formatter else 'no formatting'}: "
      f"{len(failures)} problem(s)", file=sys.stderr)
sys.exit(1 if failures else 0)
