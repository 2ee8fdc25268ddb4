// io: the pixel list and output buffer of the render entry points (bindings 5 and 6).

// Pixel list (the passes) or packed points (eval_points).
@group(0) @binding(5) var<storage, read> list: array<u32>;
// Output: (r, g, b, visible depth) per pixel (the passes, volume_march) or (r, g, b, sigma) per
// point (eval_points).
@group(0) @binding(6) var<storage, read_write> frame: array<vec4<f32>>;
