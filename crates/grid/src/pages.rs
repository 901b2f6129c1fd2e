//! Arrays whose memory is the process's own from the start.

/// `v` with one element in every page overwritten by `make()` (the value it holds, for the
/// callers here), so that each page is backed by memory of its own before the run starts.
///
/// A large vector of zeros (`vec![0; n]`, and collected atomics set to zero, which LLVM turns
/// into the same `calloc`) starts as pages that all map the kernel's shared zero page. The
/// first write to each is a copy-on-write fault, and in a process whose threads run on
/// several cores the kernel must then flush that page from every other core's TLB: an
/// interrupt to each, a VM exit on a virtual machine, while the interrupted thread steps
/// orbits. The engine's per-cell arrays would take up to hundreds of these in a fast-PSS run
/// (figures: docs/performance.md).
pub(crate) fn owned<T>(mut v: Vec<T>, make: impl Fn() -> T) -> Vec<T> {
    // 4 kB pages or larger: an element every 4 kB writes to each of them.
    let stride = (4096 / std::mem::size_of::<T>().max(1)).max(1);
    for i in (0..v.len()).step_by(stride) {
        // black_box: the compiler cannot know the value equals what calloc left there, so the
        // store stays.
        v[i] = std::hint::black_box(make());
    }
    v
}

#[cfg(test)]
mod tests {
    use super::owned;

    /// Minor page faults taken so far by the calling thread.
    #[cfg(target_os = "linux")]
    fn minor_faults() -> u64 {
        let stat = std::fs::read_to_string("/proc/thread-self/stat").expect("thread stat");
        // After the command name: state, ppid, pgrp, sid, tty, tpgid, flags, minflt.
        let (_, rest) = stat.rsplit_once(')').expect("stat line");
        rest.split_whitespace()
            .nth(7)
            .expect("minflt")
            .parse()
            .expect("count")
    }

    /// Writing to every page of an owned vector takes no page fault: the pages are backed
    /// already. (With transparent huge pages a zero-page vector would fault once per 2 MB
    /// and pass too; on 4 kB pages it faults 1 024 times here.)
    #[cfg(target_os = "linux")]
    #[test]
    fn owned_pages_are_written_without_faults() {
        let mut v = owned(vec![0u32; 1 << 20], || 0);
        let sum: u32 = v.iter().step_by(1024).sum();
        assert_eq!(std::hint::black_box(sum), 0);
        let before = minor_faults();
        for i in (0..v.len()).step_by(1024) {
            v[i] = std::hint::black_box(1);
        }
        let faults = minor_faults() - before;
        assert!(faults < 16, "{faults} faults writing 1 024 pages");
    }

    #[test]
    fn owned_keeps_every_value() {
        let v = owned(vec![0u32; 10_000], || 0);
        assert!(v.iter().all(|&x| x == 0));
        let w = owned(vec![7u8; 9_000], || 7);
        assert_eq!(w, vec![7u8; 9_000]);
    }
}
