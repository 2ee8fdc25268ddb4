// Gradient accumulation with native f32 atomics (wgpu's SHADER_FLOAT32_ATOMIC: Vulkan with
// VK_EXT_shader_atomic_float, Metal 3): one atomicAdd per contribution.

@group(0) @binding(3) var<storage, read_write> grad: array<atomic<f32>>;

fn add_grad(at: u32, v: f32) {
    atomicAdd(&grad[at], v);
}
