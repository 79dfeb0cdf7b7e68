#!/usr/bin/env python3
"""Volumes unlike the skull-stripped MNI brain, and their scoring against SPERR at equal bytes.

  testset.py make OUTDIR [--only NAME,...]     write the volumes (raw, x fastest) + manifest.tsv
                                               (the thin slabs slab1, slab2, slab4, slab8 only
                                               when named)
  testset.py ct OUT.raw NX NY NZ [--u16]       one CT-like i16 volume (memory benchmarks);
                                               --u16: the same + 1024 (air at 24) as u16
  testset.py ct-rgb OUT.raw NX NY NZ           its tissue classes painted as colours (u8 RGB)
  testset.py mni-up OUT.raw N [SIGMA]          the MNI volume resampled up to N³ (cubic
                                               spline, axes stretched to the cube) as u16
                                               (x 256), with seeded noise of SIGMA (default 64,
                                               a quarter of one original grey level), written
                                               slab by slab (bounded memory at any N)
  testset.py qi OUTDIR NAME DECODED.f32        Q_I and PSNR of a decoded f32 volume only
  testset.py score OUTDIR NAME DECODED.f32 BYTES
        Q_I (paper dB, mean of the peers' three X-ray views, per channel then averaged), PSNR
        (peak = the volume's value range) of a decoded f32 volume, and SPERR's at the same
        total bytes (hdf5plugin, one rate for every channel, largest size <= BYTES).

Uses the peers' own views, metrics and size search (../shared/peers/peers.py); run it with the
peers' venv python.  Sizes in the tables are % of the original sample bytes (u8: 1 byte per
sample, u16/i16: 2; RGB: 3 samples per voxel).
"""
import math
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
PEERS = os.path.join(HERE, "..", "..", "shared", "peers")
sys.path.insert(0, PEERS)
import peers  # noqa: E402


def mni():
    return peers.load_full().astype(np.float32)  # (197, 233, 189), axis 0 = x


def ct_like(shape, seed=1):
    """CT-like i16 values (HU): air -1000 everywhere outside an elliptic body that runs through
    the whole volume along z (so the first and last slices cut through it), fat/soft tissue,
    lungs, a vertebra and ribs of bone, noise."""
    nx, ny, nz = shape
    rng = np.random.default_rng(seed)
    x = (np.arange(nx) - nx / 2 + 0.5) / (nx / 2)
    y = (np.arange(ny) - ny / 2 + 0.5) / (ny / 2)
    z = (np.arange(nz) - nz / 2 + 0.5) / (nz / 2)
    # Sparse grids broadcast: a 512³ volume needs no three dense coordinate arrays.
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij", sparse=True)
    body = (X / 0.85) ** 2 + (Y / (0.62 + 0.05 * Z)) ** 2 <= 1
    inner = (X / 0.78) ** 2 + (Y / (0.55 + 0.05 * Z)) ** 2 <= 1
    v = np.full(shape, -1000.0, np.float32)
    v[body] = -90.0  # fat
    v[inner] = 40.0  # soft tissue
    for sx in (-0.38, 0.38):
        lung = ((X - sx) / 0.28) ** 2 + ((Y + 0.05) / 0.38) ** 2 + (Z / 1.6) ** 2 <= 1
        v[lung] = -820.0
    vert = (X / 0.09) ** 2 + ((Y - 0.42) / 0.09) ** 2 <= 1
    v[np.broadcast_to(vert, shape)] = 700.0
    ring = inner & ~((X / 0.74) ** 2 + (Y / (0.51 + 0.05 * Z)) ** 2 <= 1)
    rib = ring & (np.cos(9 * np.arctan2(Y, X) + 6 * Z) > 0.55)
    v[rib] = 900.0
    heart = ((X + 0.1) / 0.22) ** 2 + ((Y + 0.1) / 0.2) ** 2 + ((Z - 0.1) / 0.5) ** 2 <= 1
    v[heart] = 55.0
    v += rng.normal(0, 12, shape).astype(np.float32) * (v > -950)
    v += rng.normal(0, 4, shape).astype(np.float32) * (v <= -950)
    return np.clip(np.rint(v), -1024, 3071).astype(np.int16)


def classified_rgb(m):
    """The MNI volume's tissue classes (by intensity) painted as colours (u8 RGB)."""
    classes = np.digitize(m, [1, 40, 90, 130, 180])
    palette = np.array([[0, 0, 0], [90, 40, 30], [200, 60, 50], [230, 190, 90],
                        [250, 240, 230], [120, 180, 255]], np.uint8)
    return palette[classes]  # (x, y, z, 3)


def classified_ct_rgb(v):
    """A CT-like volume's classes (air, lung, fat, soft tissue, bone) painted as colours."""
    classes = np.digitize(v, [-900, -300, 0, 300])
    palette = np.array([[0, 0, 0], [70, 90, 140], [230, 200, 120], [200, 70, 60],
                        [245, 245, 235]], np.uint8)
    return palette[classes]


# Thin slabs (1 to 8 axial slices of MNI), made only when named with --only: the depth of the
# transform is limited by the thinnest axis, and these measure what that costs against SPERR,
# whose levels are per axis.
THIN = {f"slab{n}": n for n in (1, 2, 4, 8)}


def volumes(only=None):
    """(name, array (x, y, z[, 3]), dtype tag, description)."""
    want = lambda n: only is None or n in only  # noqa: E731
    out = []
    m = mni() if any(want(n) for n in ("mni-offset", "slab16", "slab32", "aniso",
                                       "wide16", "mni-rgb")) \
        or any(n in THIN for n in (only or ())) else None
    for name, n in THIN.items():
        if only is not None and name in only:
            out.append((name, m[:, :, 98 - n // 2:98 - n // 2 + n].astype(np.uint8), "u8",
                        f"{n} axial slice(s) of MNI across the head"))
    if want("mni-offset"):
        out.append(("mni-offset", (m + 100).astype(np.uint16), "u16",
                    "MNI + 100: every face non-zero"))
    if want("ct"):
        out.append(("ct", ct_like((192, 160, 96)), "i16",
                    "CT-like 192x160x96, air -1000, body through the z faces"))
    if want("slab16"):
        out.append(("slab16", m[:, :, 90:106].astype(np.uint8), "u8",
                    "16 axial slices of MNI across the head"))
    if want("slab32"):
        out.append(("slab32", m[:, :, 70:102].astype(np.uint8), "u8",
                    "32 axial slices of MNI across the head"))
    if want("aniso"):
        out.append(("aniso", m[20:180, 30:210:2, 10:180:3].astype(np.uint8), "u8",
                    "MNI cropped, every 2nd y and 3rd z sample: 160x90x57"))
    if want("wide16"):
        rng = np.random.default_rng(7)
        w = m * 180.0 + rng.normal(0, 30, m.shape) * (m > 0)
        X, Y, Z = np.meshgrid(*[np.arange(s) for s in m.shape], indexing="ij")
        w += 20000.0 * (((X - 98) ** 2 + (Y - 150) ** 2 + (Z - 120) ** 2) < 36)
        out.append(("wide16", np.clip(np.rint(w), 0, 65535).astype(np.uint16), "u16",
                    "MNI x 180 + noise + a 20000-bright sphere: 16-bit wide range"))
    if want("mni-rgb"):
        out.append(("mni-rgb", classified_rgb(m), "u8",
                    "MNI tissue classes painted as colours (RGB)"))
    return out


def mni_up_slabs(n, sigma=64.0, seed=7, slab=32):
    """The MNI volume resampled to n³ by its cubic spline (each axis stretched to n samples),
    times 256 plus seeded Gaussian noise of `sigma`, rounded and clipped to u16: a real
    anatomy at the size of a micro-CT, with fine-scale noise as an acquisition has. Yields
    (z0, block of shape (nz, n, n) u16, z fastest-varying last: storage order) slab by slab."""
    from scipy import ndimage
    src = mni() * 256.0  # (x, y, z)
    coef = ndimage.spline_filter(src, order=3, mode="nearest")
    rng = np.random.default_rng(seed)
    scale = [(s - 1) / max(n - 1, 1) for s in src.shape]
    xs = np.arange(n) * scale[0]
    ys = np.arange(n) * scale[1]
    for z0 in range(0, n, slab):
        zs = np.arange(z0, min(z0 + slab, n)) * scale[2]
        Z, Y, X = np.meshgrid(zs, ys, xs, indexing="ij")
        v = ndimage.map_coordinates(coef, [X, Y, Z], order=3, mode="nearest", prefilter=False)
        v += rng.normal(0.0, sigma, v.shape)
        yield z0, np.clip(np.rint(v), 0, 65535).astype("<u2")


def write_raw(arr, path):
    # (x, y, z[, c]) -> x fastest, channels interleaved per voxel
    if arr.ndim == 4:
        arr.transpose(2, 1, 0, 3).copy().tofile(path)
    else:
        arr.transpose(2, 1, 0).copy().tofile(path)


def make(outdir, only=None):
    os.makedirs(outdir, exist_ok=True)
    rows = []
    for name, arr, dt, desc in volumes(only):
        path = os.path.join(outdir, f"{name}.raw")
        write_raw(arr, path)
        ch = 3 if arr.ndim == 4 else 1
        dims = ",".join(str(s) for s in arr.shape[:3])
        rows.append(f"{name}\t{dims}\t{dt}\t{ch}\t{desc}")
        print(f"wrote {path}: {dims} {dt} x{ch}: {desc}")
    with open(os.path.join(outdir, "manifest.tsv"), "a") as f:
        f.write("\n".join(rows) + "\n")


def manifest(outdir, name):
    with open(os.path.join(outdir, "manifest.tsv")) as f:
        for line in f:
            p = line.rstrip("\n").split("\t")
            if p[0] == name:
                return [int(v) for v in p[1].split(",")], p[2], int(p[3])
    sys.exit(f"{name} not in {outdir}/manifest.tsv")


def load(outdir, name):
    dims, dt, ch = manifest(outdir, name)
    np_dt = {"u8": np.uint8, "u16": np.uint16, "i16": np.int16, "f32": np.float32}[dt]
    a = np.fromfile(os.path.join(outdir, f"{name}.raw"), dtype=np_dt).astype(np.float32)
    a = a.reshape(dims[2], dims[1], dims[0], ch).transpose(2, 1, 0, 3)
    return a, dt  # (x, y, z, c)


def qi_psnr(ref, dec):
    """Mean Q_I over channels of the peers' three views, and the PSNR with the data's range."""
    qis = []
    for c in range(ref.shape[3]):
        r = np.ascontiguousarray(ref[..., c])
        qis.append(peers.metrics(r, peers.views(r), np.ascontiguousarray(dec[..., c]))["qi_mean"])
    err = float(np.mean((dec.astype(np.float64) - ref) ** 2))
    rng = float(ref.max() - ref.min()) or 1.0
    psnr = 10 * math.log10(rng * rng / err) if err > 0 else math.inf
    return float(np.mean(qis)), psnr


def sperr_timed(chans, target, repeat=0, factors=(1.0,)):
    """SPERR on each array of `chans` (one HDF5 chunk each) at one rate, the largest total
    <= target bytes (the search starts at target·8/samples times each of `factors`); then
    `repeat` timed compressions and decompressions of all of them (decompression timed inside
    the HDF5 read). Returns (size, status, decoded arrays, compression seconds per repeat,
    decompression seconds per repeat)."""
    comp, decomp = peers.h5_codec(lambda r: peers.hdf5plugin.Sperr(rate=r, swap=True),
                                  chans[0].shape)
    nvox = sum(x.size for x in chans)
    rate, size, status = peers.fit(lambda r: sum(len(comp(x, r)[0]) for x in chans), target,
                                   2.0 ** -16, 16.0, guesses=[target * 8 / nvox * f for f in factors])
    blobs = [comp(x, rate)[0] for x in chans]
    ctimes, dtimes = [], []
    for _ in range(repeat):
        t = time.perf_counter()
        [comp(x, rate) for x in chans]
        ctimes.append(time.perf_counter() - t)
        dtimes.append(sum(decomp(b, rate)[1] for b in blobs))
    decoded = [decomp(b, rate)[0] for b in blobs]
    return size, status, decoded, ctimes, dtimes


def sperr_at(ref, target):
    """SPERR on each channel with one rate, the largest total <= target bytes."""
    chans = [np.ascontiguousarray(ref[..., c]) for c in range(ref.shape[3])]
    size, status, dec, _, _ = sperr_timed(chans, target, factors=(1.0, 0.97, 0.9))
    return size, status, np.stack(dec, axis=-1)


def score(outdir, name, decoded, nbytes):
    ref, _ = load(outdir, name)
    dec = np.fromfile(decoded, dtype="<f4").reshape(ref.shape[2], ref.shape[1], ref.shape[0],
                                                     ref.shape[3]).transpose(2, 1, 0, 3)
    q, p = qi_psnr(ref, dec)
    size, status, sdec = sperr_at(ref, nbytes)
    sq, sp = qi_psnr(ref, sdec)
    print(f"ours_qi {q:.2f} ours_psnr {p:.2f} sperr_bytes {size} sperr_status {status} "
          f"sperr_qi {sq:.2f} sperr_psnr {sp:.2f}")


def main():
    cmd = sys.argv[1]
    if cmd == "make":
        only = None
        if "--only" in sys.argv:
            only = set(sys.argv[sys.argv.index("--only") + 1].split(","))
        make(sys.argv[2], only)
    elif cmd == "ct":
        nx, ny, nz = (int(v) for v in sys.argv[3:6])
        v = ct_like((nx, ny, nz))
        if "--u16" in sys.argv:
            v = (v.astype(np.int32) + 1024).astype(np.uint16)
        write_raw(v, sys.argv[2])
    elif cmd == "ct-rgb":
        nx, ny, nz = (int(v) for v in sys.argv[3:6])
        write_raw(classified_ct_rgb(ct_like((nx, ny, nz))), sys.argv[2])
    elif cmd == "mni-up":
        n = int(sys.argv[3])
        sigma = float(sys.argv[4]) if len(sys.argv) > 4 else 64.0
        tmp = sys.argv[2] + ".partial"
        with open(tmp, "wb") as f:
            for _, block in mni_up_slabs(n, sigma):
                block.tofile(f)
        os.replace(tmp, sys.argv[2])
    elif cmd == "qi":
        ref, _ = load(sys.argv[2], sys.argv[3])
        dec = np.fromfile(sys.argv[4], dtype="<f4").reshape(
            ref.shape[2], ref.shape[1], ref.shape[0], ref.shape[3]).transpose(2, 1, 0, 3)
        q, p = qi_psnr(ref, dec)
        print(f"ours_qi {q:.3f} ours_psnr {p:.3f}")
    elif cmd == "score":
        score(sys.argv[2], sys.argv[3], sys.argv[4], int(sys.argv[5]))
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
