// Splat accumulation into a 64-bit fixed-point target (see `backend/gpu.rs` for the precision
// argument). Each value of the target (`sums`) is two u32 words, low then high, of a
// two's-complement integer in units of 1/scale; words are added with atomics and the carry out
// of the low word goes into the high word, so the sum is exact and independent of the order of
// the additions.
//
// One workgroup of 64 invocations takes RECORDS_PER_GROUP records; LANES invocations share a
// record and stride over the pixels of its clipped box.

// Twin of `SplatRecord` (backend/mod.rs): `channel_view` holds its two u16 fields, the channel
// in the low half and the view in the high half (little-endian layout).
struct Record {
    x0: i32,
    y0: i32,
    phase: u32,
    value: f32,
    channel_view: u32,
}

// Twin of `PhaseRect` (backend/mod.rs).
struct PhaseRect {
    offset: u32,
    cols: u32,
    rows: u32,
}

// Twin of `AccumulateParams` (backend/gpu.rs).
struct Params {
    width: u32,
    height: u32,
    channels: u32,
    total_width: u32,
    count: u32,
    groups_x: u32,
    scale: f32,
    // The first atlas sample the bound `atlas` window holds (phase offsets are the whole
    // atlas's).
    atlas_base: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> records: array<Record>;
@group(0) @binding(2) var<storage, read> phases: array<PhaseRect>;
@group(0) @binding(3) var<storage, read> atlas: array<f32>;
@group(0) @binding(4) var<storage, read_write> sums: array<atomic<u32>>;

const LANES: u32 = 8u;
const RECORDS_PER_GROUP: u32 = 8u;
// Footprint sides are clamped to this before any sum (the host keeps targets below it too),
// so no i32 sum below can overflow.
const MAX_SIDE: u32 = 16777216u;

@compute @workgroup_size(64)
fn accumulate(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let group = wid.y * params.groups_x + wid.x;
    let index = group * RECORDS_PER_GROUP + lid / LANES;
    if index >= params.count {
        return;
    }
    let lane = lid % LANES;
    let r = records[index];
    let rect = phases[r.phase];
    let w = i32(params.width);
    let h = i32(params.height);
    if r.x0 >= w || r.y0 >= h {
        return;
    }
    let xa = max(r.x0, 0);
    let ya = max(r.y0, 0);
    let xb = min(r.x0 + i32(min(rect.cols, MAX_SIDE)), w);
    let yb = min(r.y0 + i32(min(rect.rows, MAX_SIDE)), h);
    if xa >= xb || ya >= yb {
        return;
    }
    let cw = u32(xb - xa);
    let n = cw * u32(yb - ya);
    // First sample of the clipped box in the phase.
    let k0 = u32(xa - r.x0);
    let l0 = u32(ya - r.y0);
    let channel = r.channel_view & 0xffffu;
    let column0 = (r.channel_view >> 16u) * params.width + u32(xa);
    for (var i = lane; i < n; i += LANES) {
        let dx = i % cw;
        let dy = i / cw;
        let s = atlas[rect.offset - params.atlas_base + (l0 + dy) * rect.cols + k0 + dx];
        // The product rounds as the CPU's does; the power-of-two scale is exact.
        let t = round(r.value * s * params.scale);
        if t == 0.0 {
            continue;
        }
        var lo: u32;
        var hi: u32;
        if abs(t) < 2147483648.0 {
            let v = i32(t);
            lo = bitcast<u32>(v);
            hi = select(0u, 0xffffffffu, v < 0);
        } else {
            // |t| ≥ 2^31: its ulp is ≥ 2^8, so the low part (< 2^32) is exact in f32.
            let hf = floor(t * (1.0 / 4294967296.0));
            lo = u32(t - hf * 4294967296.0);
            hi = bitcast<u32>(i32(hf));
        }
        let pixel = (u32(ya) + dy) * params.total_width + column0 + dx;
        let at = 2u * (pixel * params.channels + channel);
        let old = atomicAdd(&sums[at], lo);
        let carry = select(0u, 1u, old + lo < old);
        let up = hi + carry;
        if up != 0u {
            atomicAdd(&sums[at + 1u], up);
        }
    }
}
