//! libtorch's failures as errors. tch's tensor methods panic when libtorch fails, an allocation
//! out of memory above all, so a size that a user chose (a frame size, a batch, a clip length)
//! could end a command with a panic, or cost the server a request's backtrace. Allocations that
//! a user's sizes decide go through tch's fallible `f_` calls ([`alloc_error`] names the shape,
//! its bytes and the device), [`probe`] checks early that a size can be held at all, and the work
//! behind them (encode, sampler, decode, a forward pass) runs in [`guarded`], which turns a
//! libtorch panic into an error saying what was being done.

use std::cell::Cell;
use std::panic::{self, AssertUnwindSafe};
use std::sync::Once;

use anyhow::{anyhow, Result};
use tch::{Device, Kind, TchError, Tensor};

thread_local! {
    /// [`guarded`] calls open on this thread: their libtorch panics become errors, unreported.
    static GUARDS: Cell<usize> = const { Cell::new(0) };
}

static QUIET_HOOK: Once = Once::new();

/// libtorch's message in a panic of tch's (`called `Result::unwrap()` on an `Err` value:
/// Torch("...")`), its first line (the rest is libtorch's C++ backtrace).
fn torch_message(payload: &(dyn std::any::Any + Send)) -> Option<String> {
    let text = payload.downcast_ref::<String>().map(String::as_str).or_else(|| payload.downcast_ref::<&str>().copied())?;
    let start = text.find("Torch(\"")? + "Torch(\"".len();
    let end = text.rfind("\")").filter(|&e| e >= start)?;
    // The Debug form of the message: escapes undone.
    let mut out = String::new();
    let mut chars = text[start..end].chars();
    while let Some(c) = chars.next() {
        if c != '\\' {
            out.push(c);
            continue;
        }
        match chars.next() {
            Some('n') => out.push('\n'),
            Some('t') => out.push('\t'),
            Some(other) => out.push(other),
            None => {}
        }
    }
    Some(first_line(&out))
}

fn first_line(s: &str) -> String {
    s.lines().map(str::trim).find(|l| !l.is_empty()).unwrap_or("").to_string()
}

/// Keeps the panic report of a libtorch panic that [`guarded`] turns into an error off stderr;
/// every other panic is reported by the hook that was there before.
fn install_quiet_hook() {
    QUIET_HOOK.call_once(|| {
        let previous = panic::take_hook();
        panic::set_hook(Box::new(move |info| {
            if GUARDS.with(Cell::get) > 0 && torch_message(info.payload()).is_some() {
                return;
            }
            previous(info)
        }));
    });
}

/// Runs `body`; a libtorch failure inside it (a panic of tch's) is returned as the error
/// `"{what}: {libtorch's message}"` instead of unwinding further. Other panics go on unwinding.
pub fn guarded<T>(what: impl FnOnce() -> String, body: impl FnOnce() -> Result<T>) -> Result<T> {
    install_quiet_hook();
    GUARDS.with(|g| g.set(g.get() + 1));
    let out = panic::catch_unwind(AssertUnwindSafe(body));
    GUARDS.with(|g| g.set(g.get() - 1));
    match out {
        Ok(result) => result,
        Err(payload) => match torch_message(&*payload) {
            Some(message) => Err(anyhow!("{}: {message}", what())),
            None => panic::resume_unwind(payload),
        },
    }
}

/// Bytes of a tensor of `shape` and `kind`; None when they overflow.
pub fn bytes(shape: &[i64], kind: Kind) -> Option<u128> {
    shape.iter().try_fold(kind.elt_size_in_bytes() as u128, |n, &d| n.checked_mul(u128::try_from(d).ok()?))
}

/// A byte count for people: `277.1 TB`.
pub fn human_bytes(n: u128) -> String {
    let units = ["bytes", "kB", "MB", "GB", "TB", "PB", "EB"];
    let mut value = n as f64;
    let mut unit = 0;
    while value >= 1000.0 && unit + 1 < units.len() {
        value /= 1000.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{n} bytes")
    } else {
        format!("{value:.1} {}", units[unit])
    }
}

/// `[1, 48, 21, 65536, 65536] f32 (277.1 TB)`.
pub fn describe(shape: &[i64], kind: Kind) -> String {
    let name = match kind {
        Kind::Float => "f32".to_string(),
        Kind::BFloat16 => "bf16".to_string(),
        Kind::Half => "f16".to_string(),
        Kind::Uint8 => "u8".to_string(),
        k => format!("{k:?}").to_lowercase(),
    };
    match bytes(shape, kind) {
        Some(n) => format!("{shape:?} {name} ({})", human_bytes(n)),
        None => format!("{shape:?} {name} (more bytes than a 128-bit count holds)"),
    }
}

/// The error of a failed `f_` allocation of `shape`: `"{what} {shape} cannot be allocated on
/// {device}: {libtorch's message}"`.
pub fn alloc_error(what: &str, shape: &[i64], kind: Kind, device: Device, e: TchError) -> anyhow::Error {
    let message = match e {
        TchError::Torch(m) => first_line(&m),
        other => other.to_string(),
    };
    anyhow!("{what} {} cannot be allocated on {}: {message}", describe(shape, kind), device_name(device))
}

pub fn device_name(device: Device) -> String {
    match device {
        Device::Cuda(i) => format!("cuda:{i}"),
        Device::Cpu => "cpu".into(),
        d => format!("{d:?}").to_lowercase(),
    }
}

/// Checks that a tensor of `shape` could be allocated on `device`, without writing to it: the
/// allocation is made (uninitialized) and released. An impossible size fails here at once, with
/// the error of [`alloc_error`], instead of deep inside the work it would size.
pub fn probe(what: &str, shape: &[i64], kind: Kind, device: Device) -> Result<()> {
    if shape.iter().any(|&d| d < 0) || shape.iter().try_fold(1i64, |n, &d| n.checked_mul(d)).is_none() {
        anyhow::bail!("{what} {} has more elements than a tensor can hold", describe(shape, kind));
    }
    Tensor::f_empty(shape, (kind, device)).map(drop).map_err(|e| alloc_error(what, shape, kind, device, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_libtorch_panic_in_a_guard_is_an_error_saying_what_failed() {
        let huge = [1i64 << 20, 1 << 20, 16];
        let e = guarded(|| "making the huge tensor".into(), || Ok(Tensor::zeros(huge, (Kind::Float, Device::Cpu)))).unwrap_err().to_string();
        assert!(e.starts_with("making the huge tensor: "), "{e}");
        assert!(e.contains("allocate"), "libtorch's message, first line: {e}");
        assert!(!e.contains('\n'), "{e}");
        // Work that succeeds, or fails with an error of its own, is left alone.
        assert_eq!(guarded(|| unreachable!(), || Ok(3)).unwrap(), 3);
        assert_eq!(guarded(|| unreachable!(), || -> Result<()> { anyhow::bail!("own") }).unwrap_err().to_string(), "own");
    }

    #[test]
    fn other_panics_go_on_unwinding() {
        let caught = panic::catch_unwind(|| guarded(|| "x".into(), || -> Result<()> { panic!("a bug") }));
        let payload = caught.expect_err("the panic is not an error");
        assert_eq!(payload.downcast_ref::<&str>(), Some(&"a bug"));
    }

    #[test]
    fn impossible_sizes_are_named_with_their_bytes() {
        let e = probe("the latents", &[1, 48, 21, 65536, 65536], Kind::Float, Device::Cpu).unwrap_err().to_string();
        assert!(e.starts_with("the latents [1, 48, 21, 65536, 65536] f32 (17.3 TB) cannot be allocated on cpu: "), "{e}");
        let e = probe("the frames", &[1 << 40, 1 << 40], Kind::Float, Device::Cpu).unwrap_err().to_string();
        assert!(e.contains("more elements than a tensor can hold"), "{e}");
        assert!(probe("a frame", &[3, 32, 32], Kind::Float, Device::Cpu).is_ok());
        assert_eq!(human_bytes(999), "999 bytes");
        assert_eq!(human_bytes(1_500_000), "1.5 MB");
    }
}
