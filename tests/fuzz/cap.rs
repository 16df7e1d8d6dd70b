//! An allocator that refuses what no input may ask for: one allocation above [`MAX_ONE`], or
//! more than [`MAX_LIVE`] alive at once. A refused allocation aborts the process ("memory
//! allocation of N bytes failed"), which fails the run; the input is in `<target>-current.bin`.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

/// Above the largest decoded image the crate accepts (`input::MAX_DECODED_BYTES`, 512 MiB).
pub const MAX_ONE: usize = 768 << 20;
pub const MAX_LIVE: usize = 4 << 30;

static LIVE: AtomicUsize = AtomicUsize::new(0);

pub struct Capped;

fn admit(size: usize) -> bool {
    if size > MAX_ONE {
        return false;
    }
    if LIVE.fetch_add(size, Ordering::Relaxed) + size > MAX_LIVE {
        LIVE.fetch_sub(size, Ordering::Relaxed);
        return false;
    }
    true
}

// SAFETY: every call is forwarded to the system allocator unchanged, or refused with null
// (what GlobalAlloc allows); the counter only tracks sizes.
unsafe impl GlobalAlloc for Capped {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if !admit(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: the caller's contract of GlobalAlloc, passed on to the system allocator unchanged
        let p = unsafe { System.alloc(layout) };
        if p.is_null() {
            LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if !admit(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: the caller's contract of GlobalAlloc, passed on to the system allocator unchanged
        let p = unsafe { System.alloc_zeroed(layout) };
        if p.is_null() {
            LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: the caller's contract of GlobalAlloc, passed on to the system allocator unchanged
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::Relaxed);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let old = layout.size();
        if new_size > MAX_ONE || (new_size > old && !admit(new_size - old)) {
            return std::ptr::null_mut();
        }
        // SAFETY: the caller's contract of GlobalAlloc, passed on to the system allocator unchanged
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if p.is_null() {
            if new_size > old {
                LIVE.fetch_sub(new_size - old, Ordering::Relaxed);
            }
        } else if new_size < old {
            LIVE.fetch_sub(old - new_size, Ordering::Relaxed);
        }
        p
    }
}
