// Display pass: the fixed-point accumulation target to an RGBA8 image with window/level,
// optionally through a 3×3 colour matrix plus a per-pixel RGB offset (the coded colour space
// back to RGB). The mapping is the one of `Image::to_rgba8` (image.rs).

// Twin of `DisplayUniform` (backend/gpu.rs).
struct DisplayUniform {
    total_width: u32,
    height: u32,
    channels: u32,
    // bit 0: apply `m0..m2`; bit 1: add `bias`.
    flags: u32,
    inv_scale: f32,
    low: f32,
    inv_range: f32,
    pad: f32,
    m0: vec4<f32>,
    m1: vec4<f32>,
    m2: vec4<f32>,
}

@group(0) @binding(0) var<uniform> params: DisplayUniform;
@group(0) @binding(1) var<storage, read> sums: array<u32>;
@group(0) @binding(2) var<storage, read> bias: array<f32>;
@group(0) @binding(3) var out_image: texture_storage_2d<rgba8unorm, write>;

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

fn level(x: f32) -> f32 {
    let t = clamp((x - params.low) * params.inv_range, 0.0, 1.0);
    // Quantized here so that the unorm store cannot round differently.
    return round(t * 255.0) / 255.0;
}

@compute @workgroup_size(8, 8)
fn display(@builtin(global_invocation_id) id: vec3<u32>) {
    if id.x >= params.total_width || id.y >= params.height {
        return;
    }
    let pixel = id.y * params.total_width + id.x;
    var c = vec3<f32>(0.0);
    if params.channels == 1u {
        c = vec3<f32>(value(pixel));
    } else {
        let base = pixel * params.channels;
        c = vec3<f32>(value(base), value(base + 1u), value(base + 2u));
    }
    if (params.flags & 1u) != 0u {
        c = vec3<f32>(dot(params.m0.xyz, c), dot(params.m1.xyz, c), dot(params.m2.xyz, c));
    }
    if (params.flags & 2u) != 0u {
        c += vec3<f32>(bias[3u * pixel], bias[3u * pixel + 1u], bias[3u * pixel + 2u]);
    }
    textureStore(out_image, vec2<u32>(id.xy), vec4<f32>(level(c.x), level(c.y), level(c.z), 1.0));
}
