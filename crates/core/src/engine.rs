//! Engine choices that change speed, never results: which compiled copy of the batched drivers
//! runs, and whether a forecast may guide a run's speculation. The application sets them once
//! ([`configure`], the command line from its flags or the environment); the libraries read no
//! environment, so a library user gets the defaults unless it says otherwise.

use std::sync::atomic::{AtomicBool, Ordering};

/// The engine choices of this process.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EngineChoices {
    /// Run only the copies compiled for the pinned target level (AVX2 + FMA), even where the
    /// host has AVX-512 (for comparisons: the results are the same to the bit).
    pub pinned_simd: bool,
    /// Let a run take the labels of an earlier run of its sweep as a forecast of which cells
    /// an orbit will label (the same labels either way; fewer steps dropped).
    pub forecasts: bool,
}

impl Default for EngineChoices {
    fn default() -> Self {
        EngineChoices {
            pinned_simd: false,
            forecasts: true,
        }
    }
}

static PINNED_SIMD: AtomicBool = AtomicBool::new(false);
static FORECASTS: AtomicBool = AtomicBool::new(true);

/// Sets this process's engine choices (before the first run: a driver reads them as it
/// starts).
pub fn configure(choices: EngineChoices) {
    PINNED_SIMD.store(choices.pinned_simd, Ordering::Relaxed);
    FORECASTS.store(choices.forecasts, Ordering::Relaxed);
}

/// This process's engine choices ([`EngineChoices::default`] until [`configure`]d).
pub fn choices() -> EngineChoices {
    EngineChoices {
        pinned_simd: PINNED_SIMD.load(Ordering::Relaxed),
        forecasts: FORECASTS.load(Ordering::Relaxed),
    }
}

/// CPU time of the calling thread, in nanoseconds (0 where the clock cannot be read): what
/// a calibration of the engines' speed measures. Here because it takes the workspace's one
/// `unsafe` system call outside the drivers.
pub fn thread_cpu_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec through a valid pointer.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return 0;
    }
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tangent_map::batch::Isa;

    /// The drivers' instruction set follows the choice (either choice gives the same bits, so
    /// other tests running meanwhile are unaffected).
    #[test]
    fn the_simd_choice_reaches_the_drivers() {
        configure(EngineChoices {
            pinned_simd: true,
            ..EngineChoices::default()
        });
        assert_eq!(Isa::detect(), Isa::Pinned);
        assert!(choices().pinned_simd && choices().forecasts);
        configure(EngineChoices::default());
        assert_eq!(Isa::detect() == Isa::Avx512, Isa::Avx512.available());
        assert_eq!(choices(), EngineChoices::default());
    }
}
