//! Process-wide allocator tuning for frame-sized buffers.
//!
//! A frame's images and a network's activations are megabytes each and live for one frame.
//! glibc's malloc serves such sizes with fresh `mmap`s (or trims them off the heap when
//! freed), so every frame pays page faults and the kernel's zeroing for memory it had a
//! moment ago: measured at 512 x 512 (`cargo bench -p dioptra-net --bench refine`), C1R's
//! refinement took 74 ms with glibc's defaults and 49 ms with freed memory kept for reuse.
//! The renderer cannot pool every buffer it hands out, so the program keeps freed memory
//! instead: `dioptra` calls [`keep_freed_memory`] first thing, and so do the benchmarks, so
//! their figures are the daemon's. A program embedding these crates may call it too.

/// Serves allocations below 32 MB from the heap and never returns freed heap memory under
/// 1 GB to the system, so a frame loop reuses its memory. Resident memory then stays at its
/// peak working set. A no-op off Linux/glibc. Returns whether both settings took.
pub fn keep_freed_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // 32 MB is the largest mmap threshold glibc accepts on 64-bit.
        // SAFETY: mallopt only changes malloc's parameters; any value is valid to pass.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20) == 1
                && libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30) == 1
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}
