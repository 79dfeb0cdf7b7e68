"""Where `--effort fast`'s predicted depth lands (issue 57): every volume of the test set
(`testset.py make`) and the whole MNI volume, at the effort study's four rates, compressed by
`--effort fast` as it chooses and again at each depth 1–4 (`--levels M`), each scored by the
peers' Q_I. Prints one line per file and writes depth.csv (volume, rate, levels asked, levels
taken, bytes, Q_I), then per point the depth `fast` took, the best depth and what it would
gain.

    python depth_study.py WAVESPLAT_BINARY TESTSET_DIR OUT_DIR [--only a,b]

Run it with the peers' venv python, as effort_study.py.
"""

import csv
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import effort_study  # noqa: E402
import testset  # noqa: E402


def levels_of(binary, wsp):
    """The depth a file was coded at, from `wavesplat info`."""
    info = subprocess.run([binary, "info", wsp], capture_output=True, text=True, check=True)
    for line in info.stdout.splitlines():
        if "levels M = " in line:
            return int(line.split("levels M = ")[1].split(",")[0].split()[0])
    raise RuntimeError(f"no depth in `info {wsp}`")


def main():
    binary, testset_dir, out_dir = sys.argv[1:4]
    only = None
    if "--only" in sys.argv:
        only = set(sys.argv[sys.argv.index("--only") + 1].split(","))
    tmp = os.path.join(out_dir, "work")
    os.makedirs(tmp, exist_ok=True)
    summary = []
    with open(os.path.join(out_dir, "depth.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["volume", "rate_pct", "levels_asked", "levels", "bytes", "qi_db"])
        for name, args, ref, sample_bytes in effort_study.volumes(testset_dir, only):
            for rate in effort_study.RATES:
                target = int(sample_bytes * rate)
                qi = {}
                taken = None
                for asked in ["fast", "1", "2", "3", "4"]:
                    wsp = os.path.join(tmp, "depth.wsp")
                    levels = [] if asked == "fast" else ["--levels", asked]
                    run = subprocess.run([binary, "compress", *args, "--target-bytes",
                                          str(target), "--effort", "fast", *levels, "-o", wsp],
                                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                    if run.returncode != 0:
                        continue  # a depth the volume or the target does not allow
                    m = levels_of(binary, wsp)
                    q, _ = testset.qi_psnr(ref, effort_study.decoded(binary, wsp, tmp,
                                                                     ref.shape))
                    row = [name, f"{rate * 100:.2f}", asked, m, os.path.getsize(wsp), f"{q:.2f}"]
                    w.writerow(row)
                    f.flush()
                    print(" ".join(str(x) for x in row), flush=True)
                    if asked == "fast":
                        taken = (m, q)
                    else:
                        qi[m] = q
                if taken and qi:
                    best = max(qi, key=qi.get)
                    summary.append((name, rate, taken[0], best, qi[best] - taken[1]))
    print("volume rate taken best gain_db")
    for name, rate, m, best, gain in summary:
        print(f"{name} {rate * 100:.2f} {m} {best} {gain:+.2f}")


if __name__ == "__main__":
    main()
