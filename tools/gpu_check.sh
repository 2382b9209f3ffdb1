#!/usr/bin/env bash
# GPU check: the rendering tests in a GPU variant, the main job's stages timed at a reduced size, and a
# blend (plain and refined), summed up in one JSON file. Installs nothing; run it from anywhere.
#
#   tools/gpu_check.sh            # cuda_ad_rgb (MM_VARIANT to choose another); every stage ends
#                                 # within 330 s of the start (a stage cut short is reported so)
#   tools/gpu_check.sh --quick    # the smallest sizes and one test module (a check of the script itself)
#
# Writes $OUT/gpu_check.json when OUT is set, else out/gpu_check/gpu_check.json (work files beside it).
# When the variant cannot run (no CUDA driver or device), it says so on one line and runs in llvm_ad_rgb
# instead, recording the fallback in the JSON; nothing in the CPU test suite depends on this script.
set -u
cd "$(dirname "$0")/.." || exit 2
QUICK=0
for arg in "$@"; do
    case "$arg" in
        --quick) QUICK=1 ;;
        -h|--help) sed -n '2,12p' "$0"; exit 0 ;;
        *) echo "error: unknown option $arg (use --quick or nothing)" >&2; exit 2 ;;
    esac
done
REQUESTED=${MM_VARIANT:-cuda_ad_rgb}
if [ -n "${OUT:-}" ]; then DEST=$OUT; WORK=$OUT/gpu_check_work; else DEST=out/gpu_check; WORK=out/gpu_check; fi
mkdir -p "$DEST" "$WORK" || exit 2
export QUICK REQUESTED DEST WORK
exec python3 - <<'PYTHON'
import json
import os
import re
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

quick, requested = os.environ["QUICK"] == "1", os.environ["REQUESTED"]
dest, work = os.environ["DEST"], os.environ["WORK"]
t_start = time.perf_counter()
report = {"requested_variant": requested, "quick": quick, "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


#: Every stage ends by this many seconds after the start (the check must fit in ~6 minutes).
BUDGET_S = 330


def run(name, cmd, timeout, env=None):
    """Run ``cmd`` (cut at ``timeout`` or the end of :data:`BUDGET_S`, whichever is first); its
    seconds, exit status and the tail of its output, also logged to WORK/<name>.log."""
    timeout = min(timeout, BUDGET_S - (time.perf_counter() - t_start))
    if timeout < 10:
        print(f"[gpu_check] {name}: skipped (the {BUDGET_S} s budget is spent)", flush=True)
        return {"rc": "skipped", "seconds": 0.0, "tail": [f"skipped: the {BUDGET_S} s budget is spent"]}, ""
    print(f"[gpu_check] {name}: {' '.join(cmd)}", flush=True)
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env={**os.environ, **(env or {})})
        rc, out = p.returncode, p.stdout + p.stderr
    except subprocess.TimeoutExpired as e:
        rc, out = "timeout", (e.stdout or b"").decode(errors="replace") + (e.stderr or b"").decode(errors="replace")
    seconds = round(time.perf_counter() - t0, 2)
    with open(os.path.join(work, f"{name}.log"), "w") as f:
        f.write(out)
    print(f"[gpu_check] {name}: exit {rc} in {seconds} s", flush=True)
    return {"rc": rc, "seconds": seconds, "tail": out.strip().splitlines()[-3:]}, out


# 1. the variant: the requested one if it runs here, else llvm_ad_rgb (said on one line)
probe = ("import mitsuba_manifold.render, mitsuba as mi, drjit as dr; v = {!r}; mi.set_variant(v); "
         "assert not v.startswith('cuda') or dr.has_backend(dr.JitBackend.CUDA), 'no CUDA backend'; "
         "print(float(mi.Float(2.0)[0]))").format(requested)
r, out = run("probe", [sys.executable, "-c", probe], 60)
variant, report["fallback"] = requested, None
if r["rc"] != 0:
    why = (r["tail"] or ["unknown"])[-1]
    variant = "llvm_ad_rgb"
    report["fallback"] = f"{requested} unavailable ({why}); ran in {variant}"
    print(f"[gpu_check] warning: {report['fallback']}", flush=True)
report["variant"] = variant
env = {"MM_VARIANT": variant}
try:
    report["device"] = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total,driver_version",
                                       "--format=csv,noheader"], capture_output=True, text=True,
                                      timeout=20).stdout.strip() or None
except (OSError, subprocess.TimeoutExpired):
    report["device"] = None

# 2. the rendering tests in that variant
xml = os.path.join(work, "tests.xml")
RENDER_TESTS = ["test_bsdf.py", "test_ad.py", "test_integrators.py", "test_onepass.py", "test_gi_basis.py",
                "test_render_basis.py", "test_refine.py"]   # the renderer's own (not Ray's, nor the tools')
tests = [f"tests/render/{t}" for t in (RENDER_TESTS[:1] if quick else RENDER_TESTS)]
r, _ = run("tests", [sys.executable, "-m", "pytest", "-q", "-m", "render", "-p", "no:cacheprovider",
                     f"--junitxml={xml}", *tests], 90 if quick else 180, env)
counts = {"passed": 0, "failed": 0, "errors": 0, "skipped": 0}
failed = []
if os.path.exists(xml):
    for case in ET.parse(xml).getroot().iter("testcase"):
        kinds = [c.tag for c in case]
        key = "failed" if "failure" in kinds else "errors" if "error" in kinds else \
            "skipped" if "skipped" in kinds else "passed"
        counts[key] += 1
        if key in ("failed", "errors"):
            failed.append(f"{case.get('classname')}::{case.get('name')}")
report["tests"] = {**r, **counts, "modules": tests, "not_passed": failed[:20]}

# 3. the main job at a reduced size (its own stage timings), then a blend of its basis
main_out = os.path.join(work, "main")
size = (["--resolution", "8,8,16", "--res", "16", "--spp", "4", "--ref-spp", "16", "--no-denoise"] if quick
        else ["--resolution", "32,32,64", "--res", "128", "--spp", "64", "--ref-spp", "256", "--no-denoise"])
r, _ = run("main_job", [sys.executable, "tools/main.py", "--out", main_out, "--force", *size], 120 if quick else 150, env)
report["main_job"] = r
gi = os.path.join(main_out, "gi", "report.json")
if r["rc"] == 0 and os.path.exists(gi):
    with open(gi) as f:
        job = json.load(f)
    report["main_job"]["stages_s"] = job.get("stages")
    scene = next(iter(job.get("scenes", {}).values()), None) if isinstance(job.get("scenes"), dict) else None
    basis = (scene or {}).get("basis_folder")
    points = (scene or {}).get("points", [])
    mid = next((p for p in points if p.get("point") == "midpoint"), points[0] if points else None)
    if basis and mid:
        x = ",".join(f"{v:.6g}" for v in mid["x"])
        manifold = os.path.join(main_out, "manifold.npz")
        blend = [sys.executable, "tools/blend.py", "--basis", basis, "--manifold", manifold, "--x", x, "--force",
                 "--l2", "raw"]   # the summed blend: the GPU machine has no OIDN
        r, out = run("blend", blend + ["--out", os.path.join(work, "blend.exr")], 60, env)
        m = re.search(r"blend time: ([\d.]+) ms", out)
        report["blend"] = {**r, "tool_ms": float(m.group(1)) if m else None}
        r, out = run("blend_refine", blend + ["--out", os.path.join(work, "refined.exr"), "--refine",
                                             "4" if quick else "64"], 90, env)
        report["blend_refine"] = r
    else:
        report["blend"] = {"rc": "skipped", "why": "the main job's report names no basis or point"}

report["total_s"] = round(time.perf_counter() - t_start, 1)
ok = (report["tests"]["rc"] == 0 and report["main_job"]["rc"] == 0
      and report.get("blend", {}).get("rc") == 0 and report.get("blend_refine", {}).get("rc") == 0)
report["ok"] = ok
path = os.path.join(dest, "gpu_check.json")
with open(path + ".tmp", "w") as f:
    json.dump(report, f, indent=1)
os.replace(path + ".tmp", path)
print(f"[gpu_check] {'ok' if ok else 'NOT ok'} in {report['total_s']} s ({variant}"
      f"{'; ' + report['fallback'] if report['fallback'] else ''}); wrote {path}", flush=True)
sys.exit(0 if ok else 1)
PYTHON
