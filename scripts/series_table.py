#!/usr/bin/env python3
"""Time series compressed together against each time point alone, and SPERR per time point.

  series_table.py WAVESPLAT OUTDIR [--groups 1,2,4,8,16] [--rates 0.25,0.5,1,2] [--only cine]

Makes two time series (numpy, seeded): `cine`, a cardiac cine MR-like short-axis stack
(128x128x12, 16 time points over one heart beat: a left ventricle whose blood pool contracts
and whose wall thickens, a right ventricle, static chest wall, lungs and spine, Rician-like
noise), and `perfusion`, a 4D perfusion-like series (96x96x24, 16 time points: a static head
with a contrast bolus, a gamma-variate curve, passing through the vessels and, delayed and
weaker, a tissue region). Each is written as one raw f32 file (x fastest, then y, z, t) and
compressed by `wavesplat compress FILE --dims X,Y,Z,T --dtype f32 --target-bytes B
--time-group G` at byte targets of RATE % of the series' samples at two bytes each; every time
point is decoded (`decompress --time-point`) and scored with the peers' own metrics
(../shared/peers/peers.py: Q_I, the mean of three X-ray views, and PSNR at peak 255 of a
volume scaled to 0..255 as the peers score u8 volumes). SPERR compresses each time point on its
own (hdf5plugin, one rate for all, the largest total <= B). Prints a table and writes
OUTDIR/series.csv; for each group G > 1, the bytes G = 1 needs for the same mean Q_I
(interpolated in log bytes along its curve) against G's bytes.

Run with the peers' venv python (scripts/series-table.sh does it).
"""
import csv
import math
import os
import subprocess
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "shared", "peers"))
import peers  # noqa: E402


def smooth_disc(X, Y, cx, cy, r, soft=1.5):
    """A disc of radius r (voxels) with an edge soft over ~`soft` voxels."""
    d = np.sqrt((X - cx) ** 2 + (Y - cy) ** 2)
    return 1.0 / (1.0 + np.exp((d - r) / (soft / 2.5)))


def cine(points=16, shape=(128, 128, 12), seed=7):
    nx, ny, nz = shape
    rng = np.random.default_rng(seed)
    X, Y = np.meshgrid(np.arange(nx) + 0.5, np.arange(ny) + 0.5, indexing="ij")
    out = np.zeros((points, nz, ny, nx), np.float32)
    for t in range(points):
        # One beat: the blood pool shrinks by a third and the wall thickens, then back.
        squeeze = 0.5 * (1 - math.cos(2 * math.pi * t / points))
        for z in range(nz):
            taper = 1.0 - 0.4 * abs(z - nz / 2) / nz
            v = 220 * smooth_disc(X, Y * 1.25, nx / 2, ny / 2 * 1.25, 58, 3)  # chest wall/fat
            v -= 150 * smooth_disc(X, Y, nx * 0.28, ny * 0.5, 22, 2)  # lungs
            v -= 150 * smooth_disc(X, Y, nx * 0.75, ny * 0.46, 20, 2)
            v += 250 * smooth_disc(X, Y, nx * 0.5, ny * 0.86, 7, 1.5)  # spine
            cx, cy = nx * 0.55, ny * 0.45
            r_pool = (15 - 5.5 * squeeze) * taper
            r_wall = r_pool + (6 + 3.5 * squeeze) * taper
            v += 90 * smooth_disc(X, Y, cx, cy, r_wall, 1.5)  # myocardium
            v += 380 * smooth_disc(X, Y, cx, cy, r_pool, 1.5)  # LV blood pool
            v += 300 * smooth_disc(X, Y, cx - 19, cy + 3, (11 - 3 * squeeze) * taper, 1.5)  # RV
            v = np.maximum(v, 0)
            noise = rng.normal(0, 6, v.shape) + 1j * rng.normal(0, 6, v.shape)
            out[t, z] = np.abs(v + noise).T.astype(np.float32)
    return out


def perfusion(points=16, shape=(96, 96, 24), seed=11):
    nx, ny, nz = shape
    rng = np.random.default_rng(seed)
    x = (np.arange(nx) + 0.5) / nx * 2 - 1
    y = (np.arange(ny) + 0.5) / ny * 2 - 1
    z = (np.arange(nz) + 0.5) / nz * 2 - 1
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")

    def ell(cx, cy, cz, rx, ry, rz):
        return ((X - cx) / rx) ** 2 + ((Y - cy) / ry) ** 2 + ((Z - cz) / rz) ** 2 <= 1

    base = np.zeros((nz, ny, nx), np.float32)
    base[ell(0, 0, 0, 0.85, 0.95, 0.9)] = 300  # scalp
    base[ell(0, 0, 0, 0.78, 0.88, 0.83)] = 500  # grey matter
    base[ell(0, 0, 0, 0.6, 0.7, 0.65)] = 420  # white matter
    base[ell(0.2, 0.05, 0, 0.12, 0.3, 0.5)] = 600  # ventricle
    base[ell(-0.2, 0.05, 0, 0.12, 0.3, 0.5)] = 600
    vessels = ell(0, -0.5, 0, 0.06, 0.06, 0.9) | ell(0.45, 0.1, 0, 0.05, 0.05, 0.8)
    tissue = ell(-0.35, -0.2, 0.1, 0.25, 0.2, 0.3)

    def gamma_variate(t, t0, peak):
        s = max(0.0, t - t0)
        return peak * (s / 3.0) ** 2 * math.exp(2 * (1 - s / 3.0)) if s > 0 else 0.0

    out = np.zeros((points, nz, ny, nx), np.float32)
    for t in range(points):
        v = base.copy()
        v[vessels] += gamma_variate(t, 2.0, 500)
        v[tissue] += gamma_variate(t, 3.5, 120)
        out[t] = np.maximum(v + rng.normal(0, 8, v.shape), 0).astype(np.float32)
    return out


DATASETS = {"cine": cine, "perfusion": perfusion}


def as_x_first(vol_zyx):
    """A (z, y, x) array as the peers index volumes: axis 0 = x."""
    return np.ascontiguousarray(vol_zyx.transpose(2, 1, 0))


def to_u8_scale(series):
    """The factor that maps the series' range to 0..255, as the peers' u8 volumes are."""
    top = float(series.max()) or 1.0
    return 255.0 / top


def score(ref, dec, scale):
    r = as_x_first(ref) * scale
    d = as_x_first(dec) * scale
    m = peers.metrics(r, peers.views(r), d)
    return m["qi_mean"], m["psnr_db"]


def ours(w, raw, shape, points, target, group, tmp, series, scale):
    nx, ny, nz = shape
    out = os.path.join(tmp, f"s_g{group}.wsp")
    subprocess.run(
        [w, "compress", raw, "--dims", f"{nx},{ny},{nz},{points}", "--dtype", "f32",
         "--target-bytes", str(target), "--time-group", str(group), "-o", out],
        check=True, capture_output=True)
    size = os.path.getsize(out)
    qis, psnrs = [], []
    for t in range(points):
        dec_path = os.path.join(tmp, "t.f32")
        subprocess.run([w, "decompress", out, "--time-point", str(t), "-o", dec_path],
                       check=True, capture_output=True)
        dec = np.fromfile(dec_path, dtype="<f4").reshape(nz, ny, nx)
        q, p = score(series[t], dec, scale)
        qis.append(q)
        psnrs.append(p)
    return size, float(np.mean(qis)), float(np.min(qis)), float(np.mean(psnrs))


def sperr(series, target, scale):
    sys.path.insert(0, HERE)
    import testset  # noqa: E402  (the SPERR size search the test-set table uses)
    points = series.shape[0]
    share = target // points
    total, qis, psnrs = 0, [], []
    for t in range(points):
        x = as_x_first(series[t])
        size, _status, dec, _, _ = testset.sperr_timed([x], share, factors=(1.0, 0.97, 0.9))
        total += size
        d = dec[0].transpose(2, 1, 0)
        q, p = score(series[t], d, scale)
        qis.append(q)
        psnrs.append(p)
    return total, float(np.mean(qis)), float(np.min(qis)), float(np.mean(psnrs))


def bytes_for(curve, q):
    """Bytes the (bytes, mean Q_I) `curve` needs for mean Q_I `q`, interpolated in log bytes;
    None outside it."""
    pts = sorted(curve, key=lambda p: p[1])
    for (b0, q0), (b1, q1) in zip(pts, pts[1:]):
        if q0 <= q <= q1 and q1 > q0:
            f = (q - q0) / (q1 - q0)
            return math.exp(math.log(b0) + f * (math.log(b1) - math.log(b0)))
    return None


def main():
    w, outdir = sys.argv[1], sys.argv[2]
    args = sys.argv[3:]

    def opt(name, default):
        return args[args.index(name) + 1] if name in args else default

    groups = [int(g) for g in opt("--groups", "1,2,4,8,16").split(",")]
    rates = [float(r) for r in opt("--rates", "0.25,0.5,1,2").split(",")]
    only = opt("--only", ",".join(DATASETS)).split(",")
    os.makedirs(outdir, exist_ok=True)
    rows = []
    for name in only:
        series = DATASETS[name]()
        points, nz, ny, nx = series.shape
        raw = os.path.join(outdir, f"{name}.f32")
        series.astype("<f4").tofile(raw)
        scale = to_u8_scale(series)
        samples = series.size
        print(f"# {name}: {nx}x{ny}x{nz}, {points} time points, {samples} samples", flush=True)
        print("rate %  | target B | " + " | ".join(f"G={g}: bytes, mean/min Q_I" for g in groups)
              + " | SPERR per time point: bytes, mean/min Q_I", flush=True)
        curves = {g: [] for g in groups}
        for rate in rates:
            target = int(samples * 2 * rate / 100)
            cells = []
            for g in groups:
                size, q, qmin, p = ours(w, raw, (nx, ny, nz), points, target, g, outdir, series,
                                        scale)
                curves[g].append((size, q))
                rows.append([name, rate, target, f"G{g}", size, f"{q:.3f}", f"{qmin:.3f}",
                             f"{p:.3f}"])
                cells.append(f"{size} B, {q:.2f}/{qmin:.2f}")
            size, q, qmin, p = sperr(series, target, scale)
            rows.append([name, rate, target, "SPERR", size, f"{q:.3f}", f"{qmin:.3f}", f"{p:.3f}"])
            cells.append(f"{size} B, {q:.2f}/{qmin:.2f}")
            print(f"{rate:6} | {target:8} | " + " | ".join(cells), flush=True)
        if 1 in curves:
            for g in groups:
                if g == 1:
                    continue
                for size, q in curves[g]:
                    alone = bytes_for(curves[1], q)
                    ratio = f"{size / alone:.3f}" if alone else "outside G=1's curve"
                    print(f"{name} G={g}: {size} B at Q_I {q:.2f}; G=1 needs "
                          f"{alone and round(alone)} B: ratio {ratio}", flush=True)
    with open(os.path.join(outdir, "series.csv"), "w", newline="") as f:
        c = csv.writer(f)
        c.writerow(["series", "rate_pct", "target_bytes", "coder", "bytes", "mean_qi_db",
                    "min_qi_db", "mean_psnr_db"])
        c.writerows(rows)


if __name__ == "__main__":
    main()
