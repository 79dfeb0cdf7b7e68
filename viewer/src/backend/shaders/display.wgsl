// Display pass: the fixed-point accumulation target to an RGBA8 image with window/level,
// optionally through a 3×3 colour matrix and a per-pixel offset (the coded values back to what
// the volume holds), the views laid out as `cols` panels per row. The mapping is the one of
// `Image::to_rgba8` (image.rs). A second entry point, `sample`, writes the same values (before
// the window) of every `stride`-th pixel to a buffer: what the automatic window is computed from.

// Twin of `DisplayUniform` (backend/gpu/display.rs).
struct DisplayUniform {
    // The accumulated target: all views side by side.
    total_width: u32,
    height: u32,
    channels: u32,
    // bit 0: apply `m0..m2`; bit 1: add `bias` (`channels` values per pixel).
    flags: u32,
    inv_scale: f32,
    low: f32,
    inv_range: f32,
    // Width of one view (one panel).
    view_width: u32,
    // Panels per row of the output; the output's size.
    cols: u32,
    out_width: u32,
    out_height: u32,
    // `sample`: pixels between two samples, and how many samples.
    stride: u32,
    samples: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
    m0: vec4<f32>,
    m1: vec4<f32>,
    m2: vec4<f32>,
}

@group(0) @binding(0) var<uniform> params: DisplayUniform;
@group(0) @binding(1) var<storage, read> sums: array<u32>;
@group(0) @binding(2) var<storage, read> bias: array<f32>;
@group(0) @binding(3) var out_image: texture_storage_2d<rgba8unorm, write>;
@group(0) @binding(4) var<storage, read_write> out_samples: array<f32>;

// Value `i` of the target as a float.
fn value(i: u32) -> f32 {
    let lo = sums[2u * i];
    let hi = sums[2u * i + 1u];
    var v: f32;
    if (hi == 0u && lo < 0x80000000u) || (hi == 0xffffffffu && lo >= 0x80000000u) {
        // Fits in 32 bits: convert directly (the split below would cancel).
        v = f32(bitcast<i32>(lo));
    } else {
        v = f32(bitcast<i32>(hi)) * 4294967296.0 + f32(lo);
    }
    return v * params.inv_scale;
}

// The shown value of target pixel `pixel`: grey repeated, or the colour through the matrix, plus
// the pixel's offset.
fn shown(pixel: u32) -> vec3<f32> {
    var c = vec3<f32>(0.0);
    if params.channels == 1u {
        c = vec3<f32>(value(pixel));
        if (params.flags & 2u) != 0u {
            c += vec3<f32>(bias[pixel]);
        }
        return c;
    }
    let base = pixel * 3u;
    c = vec3<f32>(value(base), value(base + 1u), value(base + 2u));
    if (params.flags & 1u) != 0u {
        c = vec3<f32>(dot(params.m0.xyz, c), dot(params.m1.xyz, c), dot(params.m2.xyz, c));
    }
    if (params.flags & 2u) != 0u {
        c += vec3<f32>(bias[base], bias[base + 1u], bias[base + 2u]);
    }
    return c;
}

fn level(x: f32) -> f32 {
    let t = clamp((x - params.low) * params.inv_range, 0.0, 1.0);
    // Quantized here so that the unorm store cannot round differently.
    return round(t * 255.0) / 255.0;
}

@compute @workgroup_size(8, 8)
fn display(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= params.out_width || id.y >= params.out_height {
        return;
    }
    let views = params.total_width / params.view_width;
    let k = (id.y / params.height) * params.cols + id.x / params.view_width;
    var c = vec3<f32>(0.0);
    if k < views {
        let x = k * params.view_width + id.x % params.view_width;
        c = shown((id.y % params.height) * params.total_width + x);
    }
    textureStore(out_image, vec2<u32>(id.xy), vec4<f32>(level(c.x), level(c.y), level(c.z), 1.0));
}

@compute @workgroup_size(64)
fn sample(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= params.samples {
        return;
    }
    let c = shown(id.x * params.stride);
    for (var r = 0u; r < params.channels; r++) {
        out_samples[id.x * params.channels + r] = c[r];
    }
}
