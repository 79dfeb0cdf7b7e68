"""The compression-effort study (issue 57): every volume of the test set (`testset.py make`)
and the whole MNI volume, at 0.07, 0.15, 1.25 and 5.85 % of their sample bytes, compressed
with each `--effort` (wall seconds, min of REPEAT runs, and user CPU seconds of the fastest)
and scored by the peers' metrics (Q_I: the paper's dB over the peers' three X-ray views, per
channel then averaged); SPERR at the bytes of the default effort's file, its compression
timed on one thread in the same run. Writes effort.csv and, when matplotlib is there,
effort.png: per volume, each effort's points (one per rate, joined) as Q_I over SPERR's (dB)
against time over SPERR's, with the goals' lines (+1 dB, 3×).

    python effort_study.py WAVESPLAT_BINARY TESTSET_DIR OUT_DIR [REPEAT] [--only a,b]
                           [--no-sperr]
    python effort_study.py --plot OUT.png CSV [CSV ...]

Run it with the peers' venv python (scripts/effort-study.sh does).
"""

import csv
import os
import resource
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import testset  # noqa: E402
from testset import peers  # noqa: E402

RATES = [0.0007, 0.0015, 0.0125, 0.0585]
# What is compressed: a label and its flags, each point's SPERR run at the bytes of the
# "default" one. EFFORT_CONFIGS="label=flags;label=flags" replaces the three efforts (a study
# of candidates: "fast0=--effort fast --refine-rounds 0;default=--effort default").
CONFIGS = [(e, ["--effort", e]) for e in ["fast", "default", "best"]]
if os.environ.get("EFFORT_CONFIGS"):
    CONFIGS = [(label.strip(), flags.split())
               for label, flags in (c.split("=", 1) for c in
                                    os.environ["EFFORT_CONFIGS"].split(";") if c.strip())]


def timed(cmd):
    """Runs `cmd`; returns (wall seconds, user+system CPU seconds of the child)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def volumes(testset_dir, only):
    """(name, compress arguments, reference (x, y, z, c), sample bytes)."""
    out = []
    with open(os.path.join(testset_dir, "manifest.tsv")) as f:
        for line in f:
            name, dims, dt, ch = line.rstrip("\n").split("\t")[:4]
            if only and name not in only:
                continue
            ref, _ = testset.load(testset_dir, name)
            bps = {"u8": 1, "u16": 2, "i16": 2, "f32": 4}[dt]
            args = [os.path.join(testset_dir, f"{name}.raw"), "--dims", dims, "--dtype", dt,
                    "--channels", ch]
            out.append((name, args, ref, ref.size * bps))
    if not only or "mni" in only:
        ref = peers.load_full()
        out.append(("mni", [peers.DATA], ref[..., None].astype(np.float32), ref.size))
    return out


def decoded(binary, wsp, tmp, shape):
    f32 = os.path.join(tmp, "dec.f32")
    subprocess.run([binary, "decompress", wsp, "-o", f32], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    nx, ny, nz, nc = shape
    return np.fromfile(f32, dtype="<f4").reshape(nz, ny, nx, nc).transpose(2, 1, 0, 3)


def main():
    if sys.argv[1] == "--plot":
        return replot(sys.argv[3:], sys.argv[2])
    binary, testset_dir, out_dir = sys.argv[1:4]
    repeat = int(sys.argv[4]) if len(sys.argv) > 4 and sys.argv[4].isdigit() else 1
    only = None
    if "--only" in sys.argv:
        only = set(sys.argv[sys.argv.index("--only") + 1].split(","))
    os.makedirs(out_dir, exist_ok=True)
    tmp = os.path.join(out_dir, "work")
    os.makedirs(tmp, exist_ok=True)
    rows = []
    path = os.path.join(out_dir, "effort.csv")
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["volume", "rate_pct", "target_bytes", "coder", "bytes", "wall_s", "cpu_s",
                    "qi_db"])
        for name, args, ref, sample_bytes in volumes(testset_dir, only):
            for rate in RATES:
                target = int(sample_bytes * rate)
                default_bytes = None
                for effort, flags in CONFIGS:
                    wsp = os.path.join(tmp, f"{effort}.wsp")
                    cmd = [binary, "compress", *args, "--target-bytes", str(target), *flags,
                           "-o", wsp]
                    runs = [timed(cmd) for _ in range(repeat)]
                    wall, cpu = min(runs)
                    size = os.path.getsize(wsp)
                    q, _ = testset.qi_psnr(ref, decoded(binary, wsp, tmp, ref.shape))
                    if effort == "default" or default_bytes is None:
                        default_bytes = size
                    row = [name, f"{rate * 100:.2f}", target, effort, size, f"{wall:.3f}", f"{cpu:.3f}",
                           f"{q:.2f}"]
                    w.writerow(row)
                    f.flush()
                    rows.append(row)
                    print(" ".join(str(x) for x in row), flush=True)
                if "--no-sperr" in sys.argv:
                    continue
                chans = [np.ascontiguousarray(ref[..., c]) for c in range(ref.shape[3])]
                size, _, dec, ctimes, _ = testset.sperr_timed(chans, default_bytes, max(repeat, 1),
                                                              factors=(1.0, 0.97, 0.9))
                sq, _ = testset.qi_psnr(ref, np.stack(dec, axis=-1))
                row = [name, f"{rate * 100:.2f}", target, "sperr", size, f"{min(ctimes):.3f}",
                       f"{min(ctimes):.3f}", f"{sq:.2f}"]
                w.writerow(row)
                f.flush()
                rows.append(row)
                print(" ".join(str(x) for x in row), flush=True)
    print(f"CSV: {path}")
    plot(rows, os.path.join(out_dir, "effort.png"))


def plot(rows, png):
    """The picture of `rows` (the CSV's rows): see the module's doc."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.ticker import FixedLocator, NullFormatter, ScalarFormatter
    except ImportError:
        print("matplotlib not installed: no plot")
        return
    names = sorted({r[0] for r in rows}, key=[r[0] for r in rows].index)
    cols = (len(names) + 1) // 2
    fig, axes = plt.subplots(2, cols, figsize=(4 * cols, 7), squeeze=False)
    labels = [c for c in dict.fromkeys(r[3] for r in rows) if c != "sperr"]
    marks = dict(zip(labels, "os^vD<>p*h"))
    for r in rows:
        r[1] = f"{float(r[1]):.2f}"
    for ax, name in zip(axes.flat, names):
        sperr = {r[1]: r for r in rows if r[0] == name and r[3] == "sperr"}
        for coder in labels:
            pts = [(float(r[5]) / float(sperr[r[1]][5]), float(r[7]) - float(sperr[r[1]][7]))
                   for r in rows if r[0] == name and r[3] == coder and r[1] in sperr]
            if pts:
                ax.plot(*zip(*pts), marks[coder] + "-", label=coder, alpha=0.8)
        ax.axhline(1.0, color="grey", lw=0.8, ls="--")
        ax.axvline(3.0, color="grey", lw=0.8, ls=":")
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(FixedLocator([1, 2, 3, 5, 10, 20, 50, 100]))
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_title(f"{name} (0.07 to 5.85 %)")
        ax.set_xlabel("time / SPERR's")
        ax.set_ylabel("Q_I − SPERR's (dB)")
    axes.flat[0].legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    print(f"plot: {png}")


def replot(csvs, png):
    """Plots the rows of several runs' CSVs together (a study of candidates beside a run with
    SPERR's points)."""
    rows = {}
    for path in csvs:
        with open(path) as f:
            for r in list(csv.reader(f))[1:]:
                # A later run's point of the same volume, rate and coder replaces an earlier.
                rows[(r[0], f"{float(r[1]):.2f}", r[3])] = r
    plot(list(rows.values()), png)


if __name__ == "__main__":
    main()
