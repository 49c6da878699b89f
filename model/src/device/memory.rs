//! Device memory in use, read from the CUDA driver (cudarc). libtorch's caching allocator keeps
//! what it reserved, so the figure at the end of a step is the step's peak reservation.

use tch::Device;

thread_local! {
    static CONTEXTS: std::cell::RefCell<std::collections::BTreeMap<usize, std::sync::Arc<cudarc::driver::CudaContext>>> =
        Default::default();
}

/// MiB in use on `device` (all processes), or `None` on the CPU or when the driver is unavailable.
pub fn used_mib(device: Device) -> Option<f64> {
    let Device::Cuda(ordinal) = device else { return None };
    CONTEXTS.with(|c| {
        let mut map = c.borrow_mut();
        let ctx = match map.get(&ordinal) {
            Some(ctx) => ctx.clone(),
            None => {
                let ctx = cudarc::driver::CudaContext::new(ordinal).ok()?;
                map.insert(ordinal, ctx.clone());
                ctx
            }
        };
        ctx.bind_to_thread().ok()?;
        let (free, total) = cudarc::driver::result::mem_get_info().ok()?;
        Some((total - free) as f64 / (1024.0 * 1024.0))
    })
}
