//! Running out of memory ends the process with an error (exit 1, a message, unfinished outputs
//! removed) instead of Rust's abort (exit 134): under `ulimit -v` or a container's limit any
//! allocation may fail, not only the big buffers the library reserves fallibly. Stable Rust offers no
//! hook for allocation failure, so this wraps the system allocator: the one place the workspace
//! allows `unsafe`, as implementing `GlobalAlloc` requires it.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};

/// The system allocator, ending the process cleanly when an allocation fails outside
/// [`echosurf::resources::fallibly`] (whose callers turn the failure into an error themselves).
pub struct CleanOutOfMemory;

static ENDING: AtomicBool = AtomicBool::new(false);

/// Writes `n` in decimal into `buf` without allocating; returns the digits.
fn decimal(mut n: usize, buf: &mut [u8; 20]) -> &[u8] {
    let mut i = buf.len();
    loop {
        i -= 1;
        buf[i] = b'0' + (n % 10) as u8;
        n /= 10;
        if n == 0 {
            break;
        }
    }
    &buf[i..]
}

#[cold]
fn failed(layout: Layout) -> *mut u8 {
    if echosurf::resources::allocation_is_fallible() {
        return std::ptr::null_mut();
    }
    if ENDING.swap(true, Ordering::SeqCst) {
        // Failed again while ending (the clean-up allocates): end now.
        std::process::exit(1);
    }
    let mut digits = [0u8; 20];
    let mut err = std::io::stderr().lock();
    let _ = err.write_all(b"error: out of memory: an allocation of ");
    let _ = err.write_all(decimal(layout.size(), &mut digits));
    let _ = err.write_all(
        b" bytes failed (the machine's memory or an address-space limit such as `ulimit -v` is \
          exhausted); a smaller --memory-budget refuses such runs before they start\n",
    );
    drop(err);
    crate::temp_files::try_remove_in_flight();
    std::process::exit(1);
}

// SAFETY: every call forwards to `System` with the same arguments; only a null result is
// intercepted, and then either passed on (fallible callers) or the process ends.
unsafe impl GlobalAlloc for CleanOutOfMemory {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract is System's.
        let p = unsafe { System.alloc(layout) };
        if p.is_null() { failed(layout) } else { p }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as above.
        let p = unsafe { System.alloc_zeroed(layout) };
        if p.is_null() { failed(layout) } else { p }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: as above.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: as above.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if p.is_null() {
            // SAFETY: `new_size` with the old alignment is the layout the caller asked for.
            failed(unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) })
        } else {
            p
        }
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn decimal_writes_every_digit() {
        let mut buf = [0u8; 20];
        assert_eq!(super::decimal(0, &mut buf), b"0");
        assert_eq!(super::decimal(4194304, &mut buf), b"4194304");
        assert_eq!(
            super::decimal(usize::MAX, &mut buf),
            usize::MAX.to_string().as_bytes()
        );
    }
}
