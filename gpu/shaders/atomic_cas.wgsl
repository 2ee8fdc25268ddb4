// Gradient accumulation without float atomics (WebGPU core, DX12, GL): a compare-exchange loop on
// the u32 bit pattern of the f32. Each retry means another invocation added to the same entry in
// between; the sum is exact up to f32 rounding in some order, as with native atomics.

@group(0) @binding(3) var<storage, read_write> grad: array<atomic<u32>>;

fn add_grad(at: u32, v: f32) {
    var old = atomicLoad(&grad[at]);
    loop {
        let r = atomicCompareExchangeWeak(&grad[at], old, bitcast<u32>(bitcast<f32>(old) + v));
        if r.exchanged {
            break;
        }
        old = r.old_value;
    }
}
