"""Bricked compression beside chunked SPERR on one large volume (issue 55's figure "SPERR
(chunked) side by side on the same volumes"): the CT phantom at N³ (f32), or with `--volume
mni` the MNI volume resampled up to N³ as u16 (`testset.py mni-up`), compressed by
`wavesplat compress --brick B` at a fraction of its coefficients, and by SPERR through HDF5 with
B³ chunks (hdf5plugin.Sperr in rate mode, the peers' codec) at the bits per voxel that give the
same bytes. Both on one thread (RAYON_NUM_THREADS=1 and taskset; SPERR's filter is
single-threaded), timed; both decoded and scored with the peers' metrics (Q_I over two axis
views and one oblique X-ray view, `../shared/peers/peers.py`, and PSNR over the peak 255).

    VENV=/path/to/peers-venv bash scripts/brick-sperr.sh [N] [BRICK] [FRACTION] [--volume ct|mni]
                                                         [--whole]

`--whole` also compresses the volume unbricked to the bricked file's bytes (`--target-bytes`,
all threads: what bricking costs at equal bytes). CORE=K (brick-sperr.sh) pins to core K.

Writes one Markdown table row per codec on stdout and a CSV in $TMPDIR/wavesplat-brick-sperr.
Needs numpy, scipy, h5py and hdf5plugin (the peers' venv: `bash ../shared/peers/run.sh` makes
one).
"""

import csv
import math
import os
import subprocess
import sys
import time

import h5py
import hdf5plugin
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "..", "shared", "peers"))
import peers  # noqa: E402  (the peers' X-ray views and metrics, unchanged)


def run(cmd, env=None):
    t = time.perf_counter()
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


def sperr_chunked(x, bpv, chunk):
    """SPERR over HDF5 chunks of `chunk`³: bytes, compress seconds, decoded volume."""
    with h5py.File("brick-sperr.h5", "w", driver="core", backing_store=False,
                   rdcc_nbytes=0) as f:
        t = time.perf_counter()
        ds = f.create_dataset("d", data=x, chunks=(chunk,) * 3,
                              **hdf5plugin.Sperr(rate=bpv, swap=True))
        f.flush()
        secs = time.perf_counter() - t
        size = 0
        for i in range(ds.id.get_num_chunks()):
            size += ds.id.get_chunk_info(i).size
        y = ds[()]
    return size, secs, y


def main():
    flags = [a for a in sys.argv[1:] if a.startswith("--")]
    args = [a for a in sys.argv[1:] if not a.startswith("--") and a not in ("ct", "mni")]
    n = int(args[0]) if len(args) > 0 else 512
    brick = int(args[1]) if len(args) > 1 else 256
    fraction = float(args[2]) if len(args) > 2 else 0.01
    volume = "mni" if "mni" in sys.argv[1:] and "--volume" in flags else "ct"
    w = os.path.join(ROOT, "target", "release", "wavesplat")
    tmp = os.path.join(os.environ.get("TMPDIR", "/tmp"), "wavesplat-brick-sperr")
    os.makedirs(tmp, exist_ok=True)
    if volume == "ct":
        raw, dtype, label = os.path.join(tmp, f"ct{n}.f32"), "f32", f"CT phantom {n}³ f32"
        if not os.path.exists(raw):
            run([w, "phantom", "ct", "--dims", f"{n},{n},{n}", "-o", raw])
    else:
        raw, dtype, label = os.path.join(tmp, f"mni{n}.u16"), "u16", f"MNI resampled to {n}³ u16"
        if not os.path.exists(raw):
            run([sys.executable, os.path.join(HERE, "testset.py"), "mni-up", raw, str(n)])
    x = np.fromfile(raw, dtype="<f4" if dtype == "f32" else "<u2").reshape(n, n, n)  # z, y, x
    x = x.astype(np.float32, copy=False)
    env = dict(os.environ, RAYON_NUM_THREADS="1")
    one_core = ["taskset", "-c", os.environ.get("CORE", "0")]
    stem = f"{volume}{n}_b{brick}"
    ours = os.path.join(tmp, f"{stem}.wsp")
    # More `compress` flags (e.g. "--effort fast") from the environment.
    extra = os.environ.get("WAVESPLAT_FLAGS", "").split()
    src = [raw, "--dims", f"{n},{n},{n}", "--dtype", dtype]
    secs = run(one_core + [w, "compress", *src, "--brick", str(brick),
                           "--target-fraction", str(fraction), *extra, "-o", ours], env)
    size = os.path.getsize(ours)

    def decode(path):
        decoded = os.path.join(tmp, f"{stem}.decoded.f32")
        dsecs = run(one_core + [w, "decompress", path, "-o", decoded], env)
        y = np.fromfile(decoded, dtype=np.float32).reshape(n, n, n)
        os.remove(decoded)
        return y, dsecs

    y, dsecs = decode(ours)
    # The peers' metrics need the reference's views once; PSNR's peak is 255 there, so the
    # CT's Hounsfield range is mapped to [0, 255] for both (a linear map: Q_I is unchanged).
    lo, hi = float(x.min()), float(x.max())
    scale = lambda v: (v.astype(np.float64) - lo) * (255.0 / (hi - lo))  # noqa: E731
    ref = scale(x)
    refviews = peers.views(ref)
    rows = []
    m = peers.metrics(ref, refviews, scale(y))
    del y
    rows.append(("wavesplat", " ".join([f"--brick {brick} --target-fraction {fraction}", *extra]), size, secs,
                 dsecs, m))
    if "--whole" in flags:
        whole = os.path.join(tmp, f"{volume}{n}_whole.wsp")
        wsecs = run([w, "compress", *src, "--target-bytes", str(size), *extra, "-o", whole])
        y, wdsecs = decode(whole)
        m = peers.metrics(ref, refviews, scale(y))
        del y
        rows.append(("wavesplat, whole", f"--target-bytes {size}, unbricked", os.path.getsize(whole),
                     wsecs, wdsecs, m))
    bpv = size * 8.0 / x.size
    ssize, ssecs, sy = sperr_chunked(x, bpv, brick)
    m = peers.metrics(ref, refviews, scale(sy))
    del sy
    rows.append(("SPERR", f"chunks {brick}³, rate {bpv:.5f} bpv", ssize, ssecs, math.nan, m))
    out = os.path.join(tmp, f"brick_sperr_{volume}_{n}_{brick}.csv")
    with open(out, "w", newline="") as f:
        c = csv.writer(f)
        c.writerow(["codec", "setting", "bytes", "compress_s", "decompress_s", "qi_ax0",
                    "qi_ax2", "qi_obl", "qi_mean", "psnr_db"])
        for name, setting, b, s, d, mm in rows:
            c.writerow([name, setting, b, f"{s:.2f}", f"{d:.2f}", f"{mm['qi_ax0']:.2f}",
                        f"{mm['qi_ax2']:.2f}", f"{mm['qi_obl']:.2f}", f"{mm['qi_mean']:.2f}",
                        f"{mm['psnr_db']:.2f}"])
    print(f"{label}, {brick}³ bricks / chunks, one thread each, "
          f"{time.strftime('%Y-%m-%d')}")
    print()
    print("| codec | setting | bytes | compress | ns per voxel | Q_I ax0 / ax2 / oblique (mean) "
          "| PSNR |")
    print("|---|---|---|---|---|---|---|")
    for name, setting, b, s, d, mm in rows:
        print(f"| {name} | {setting} | {b} | {s:.1f} s | {s * 1e9 / x.size:.0f} | "
              f"{mm['qi_ax0']:.2f} / {mm['qi_ax2']:.2f} / {mm['qi_obl']:.2f} "
              f"({mm['qi_mean']:.2f}) dB | {mm['psnr_db']:.2f} dB |")
    print()
    print(f"CSV: {out}")


if __name__ == "__main__":
    main()
