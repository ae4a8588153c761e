//! The `nanoeye` binary's memory set-up, in one place for the binary and for the benches and
//! examples that time what it runs: linking this crate makes mimalloc the process's global
//! allocator, and [`like_cli`] sets the two process-wide options the binary sets at start-up.
//! A bench that times a stage without them measures another program's page faults.

/// mimalloc: each thread allocates from its own heap. glibc's one arena (`M_ARENA_MAX` 1, the
/// setting before) made 16 training threads queue on its lock: the main job's training took
/// 28–31 s for 20 steps on 16 cores against 18–20 s here (docs/run.md, twenty-fifth
/// session); on 2 cores the two are level.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// `mi_option_purge_delay` in mimalloc.h's option enum (the sys crate names no constant for it).
pub const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Both start-up settings of the `nanoeye` binary: [`keep_freed_memory`] and
/// [`no_transparent_huge_pages`]. Call it first thing in `main`.
pub fn like_cli() {
    keep_freed_memory();
    no_transparent_huge_pages();
}

/// Keeps freed heap memory in the process: never purged back to the kernel. The RCWA sweep
/// frees ~1 MB matrices thousands of times a second and training frees its tensors every step;
/// handed back, each would be faulted in and zeroed again (docs/bench/metalib.md). With
/// mimalloc's default delay the training stage took twice the system time and 15 % longer.
pub fn keep_freed_memory() {
    // SAFETY: sets one allocator option (an atomic store inside mimalloc).
    unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1) }
}

/// Turns transparent huge pages off for this process (`prctl(PR_SET_THP_DISABLE)`; the kernel
/// then backs even mimalloc's `MADV_HUGEPAGE` arenas with 4 KB pages). A huge page is zeroed
/// whole at its first touch, 2 MB however little of it is used, and on a VM whose memory the
/// host has not backed yet each costs the process milliseconds of system time: `search train`
/// on the default job's data, 30 steps, spent 12–14 s in the kernel with huge pages against
/// 5–6 s without (same user time) in this VM's first runs of the session; once its memory had
/// been touched the two were level (docs/run.md, thirty-first session). Nothing computed
/// depends on page sizes; user time did not change. A no-op where the call is refused.
pub fn no_transparent_huge_pages() {
    #[cfg(target_os = "linux")]
    // SAFETY: prctl with integer arguments only; it changes a flag of this process.
    unsafe {
        libc::prctl(libc::PR_SET_THP_DISABLE, 1, 0, 0, 0);
    }
}

#[cfg(test)]
mod tests {
    /// After the set-up the process has transparent huge pages off (PR_GET_THP_DISABLE is 1).
    #[cfg(target_os = "linux")]
    #[test]
    fn the_set_up_turns_transparent_huge_pages_off() {
        super::no_transparent_huge_pages();
        // SAFETY: reads a flag of this process.
        assert_eq!(
            unsafe { libc::prctl(libc::PR_GET_THP_DISABLE, 0, 0, 0, 0) },
            1
        );
    }

    /// The option index set is mimalloc's purge delay: 1000 ms by default in the mimalloc 3 the
    /// sys crate builds (a renumbered enum would show another default), −1 after.
    #[test]
    fn the_option_set_is_the_purge_delay() {
        // SAFETY: reads and sets one allocator option.
        unsafe {
            assert_eq!(
                libmimalloc_sys::mi_option_get(super::MI_OPTION_PURGE_DELAY),
                1000
            );
            super::keep_freed_memory();
            assert_eq!(
                libmimalloc_sys::mi_option_get(super::MI_OPTION_PURGE_DELAY),
                -1
            );
        }
    }
}
