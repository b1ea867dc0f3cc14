//! The C allocator's arenas, capped once at start-up (glibc only).
//!
//! glibc's malloc gives threads that contend for memory arenas of their own, up to eight per core,
//! and keeps what is freed in each arena for reuse by that arena instead of returning it to the
//! system. The daemon's threads (HTTP workers, the blocking pool serving downloads, which comes
//! and goes, the device thread, the reconstruction pool, each scan's acquisition thread) all
//! handle frames of about 1 MB, so every new arena ends up holding a few megabytes of free space
//! of its own: in a soak (a scan every few seconds, clients polling and downloading) the resident
//! size climbed for minutes (20.6 -> 39.0 MB over ten minutes; `malloc_stats` a minute into
//! another run: 15 arenas holding 20 MB, 1 MB of it in use, 5.6 MB in use in all, 8.1 MB two
//! minutes later while RSS went on rising), and with two arenas the largest RSS of
//! every minute of ten stays between 28.0 and 29.4 MB. The daemon does not allocate on hot paths
//! from many threads at once (the carving loops work on buffers allocated once), so two arenas
//! should cost it little contention (not measured).
//!
//! An explicit `MALLOC_ARENA_MAX` in the environment is left to glibc (it reads it itself).

/// What [`cap_arenas`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ArenaCap {
    /// The arenas are capped at this many.
    Capped(i32),
    /// `MALLOC_ARENA_MAX` is set: glibc follows it.
    FromEnvironment,
    /// glibc refused the setting (`mallopt` returned 0).
    Refused,
    /// Not glibc: its allocator has no such setting.
    Unsupported,
}

/// Arenas the daemon runs with.
pub const ARENAS: i32 = 2;

/// Cap glibc's malloc arenas at [`ARENAS`], unless `MALLOC_ARENA_MAX` is set. Call it first thing
/// in `main`, before any thread starts (threads already attached to an arena keep it).
pub fn cap_arenas() -> ArenaCap {
    if std::env::var_os("MALLOC_ARENA_MAX").is_some() {
        return ArenaCap::FromEnvironment;
    }
    set_arena_max(ARENAS)
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn set_arena_max(n: i32) -> ArenaCap {
    // SAFETY: mallopt only changes the allocator's parameters; M_ARENA_MAX takes any positive count.
    if unsafe { libc::mallopt(libc::M_ARENA_MAX, n) } == 1 {
        ArenaCap::Capped(n)
    } else {
        ArenaCap::Refused
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn set_arena_max(_n: i32) -> ArenaCap {
    ArenaCap::Unsupported
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glibc_takes_the_arena_cap() {
        let expected = if cfg!(all(target_os = "linux", target_env = "gnu")) {
            ArenaCap::Capped(3)
        } else {
            ArenaCap::Unsupported
        };
        assert_eq!(set_arena_max(3), expected);
    }
}
