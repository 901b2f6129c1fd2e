//! The compute side: one thread that runs the leases it is handed through the grid's tile
//! executor on the worker's rayon pool and hands back reports, releases and hunger.

use crate::signals::Signals;
use crate::source::LeaseSource;
use salient_grid::executor::{integrate_stream, LocalLedger};
use salient_grid::spec::JobSpec;
use salient_grid::{CellRun, Grid};
use salient_proto::v1;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use tokio::sync::mpsc;

/// Runs whose grid a worker keeps built at once.
const MAX_BUILT_RUNS: usize = 4;

/// A lease handed to the compute thread.
pub(crate) struct Work {
    pub(crate) lease: v1::TileRef,
    pub(crate) spec: Arc<JobSpec>,
    pub(crate) cells: Vec<u32>,
}

/// What the compute thread hands back.
pub(crate) enum Done {
    Report(v1::TileReport),
    /// Not started because the worker is draining.
    Released(v1::TileRef),
    /// A lane is idle and no leased cell waits: time for another lease.
    Hungry,
}

/// The compute side: runs every lease of one run through one stream of the tile executor
/// ([`integrate_stream`]), so lanes freed by an ended orbit take the next leased cell at once
/// whatever lease it came in, and a lease's outcomes go out as its orbits end (lease by lease,
/// each lease would wait for its longest orbit with the other lanes idle; figures:
/// docs/performance.md). A lease for another run ends the stream when the cells already
/// leased are done.
pub(crate) fn compute_thread(
    pool: rayon::ThreadPool,
    work: std::sync::mpsc::Receiver<Work>,
    done: mpsc::UnboundedSender<Done>,
    signals: Arc<Mutex<Signals>>,
    draining: Arc<AtomicBool>,
) {
    // Built grids per (job, run), each tied to the spec it was built from (a coordinator on
    // another store reuses job ids), and few: a worker moves through runs in order.
    type Built = (Arc<JobSpec>, Grid, CellRun, Arc<LocalLedger>);
    let mut runs: HashMap<(u64, u32), Built> = HashMap::new();
    let mut next: Option<Work> = None;
    loop {
        let w = match next.take() {
            Some(w) => w,
            None => match work.recv() {
                Ok(w) => w,
                Err(_) => return,
            },
        };
        if draining.load(Ordering::Relaxed) {
            let _ = done.send(Done::Released(w.lease));
            continue;
        }
        let key = w.lease.key();
        if runs
            .get(&(key.0, key.1))
            .is_some_and(|b| !Arc::ptr_eq(&b.0, &w.spec))
            || (runs.len() >= MAX_BUILT_RUNS && !runs.contains_key(&(key.0, key.1)))
        {
            runs.clear();
            // The network side made the new run's ledger (it may hold relayed outcomes).
            let keep = (key.0, key.1);
            signals
                .lock()
                .expect("signals")
                .ledgers
                .retain(|k, _| *k == keep);
        }
        let (spec, grid, cell_run, local) = runs.entry((key.0, key.1)).or_insert_with(|| {
            let grid = w.spec.grid(key.1 as usize);
            let local = signals
                .lock()
                .expect("signals")
                .ledger((key.0, key.1), &w.spec, Some(&grid))
                .local
                .clone();
            (w.spec.clone(), grid, w.spec.cell_run(key.1 as usize), local)
        });
        let source = LeaseSource::new(
            local.clone(),
            done.clone(),
            signals.clone(),
            draining.clone(),
        );
        source.add(w);
        let mode = spec.mode(key.1 as usize);
        std::thread::scope(|scope| {
            scope.spawn(|| pool.install(|| integrate_stream(grid, cell_run, mode, local, &source)));
            // Leases of the same run join the stream; another run's lease, or the network
            // side's end, closes it.
            loop {
                match work.recv() {
                    Ok(w) if draining.load(Ordering::Relaxed) => {
                        let _ = done.send(Done::Released(w.lease));
                    }
                    Ok(w)
                        if (w.lease.job, w.lease.run) == (key.0, key.1)
                            && Arc::ptr_eq(&w.spec, spec) =>
                    {
                        source.add(w);
                    }
                    Ok(w) => {
                        next = Some(w);
                        break;
                    }
                    Err(_) => break,
                }
            }
            source.close();
        });
    }
}
