//! The worker: registers with a coordinator, keeps a few tile leases, and runs the cells of
//! every lease of one run through one stream of the grid's tile executor on a rayon pool — the
//! same code `salient run` uses — so a lane freed by an ended orbit takes the next leased cell
//! whatever lease it came in. Outcomes go out in its polls as orbits end. Reports stay in an
//! outbox until acknowledged, so they survive a coordinator restart; on drain it finishes the
//! leases it started, releases the ones not started, and deregisters.
//!
//! Two sides share the work. The network side (lease_loop.rs) registers and polls: it asks for
//! leases, hands them to the compute side and sends what comes back. The compute side
//! (compute.rs) runs each run's leases through one stream whose cells come from a
//! `LeaseSource` (source.rs). What the network side learns while a lease runs (cells to skip,
//! revoked leases, other workers' outcomes) reaches the compute side through signals.rs.

mod compute;
mod lease_loop;
mod signals;
mod source;

// The rules of the lease loop and the stream that the scaling simulator (salient-sim) replays.
pub use lease_loop::{free_slots, HUNGRY_LEASES};
pub use signals::{crossings_of_held, lease_key, LeaseKey};
pub use source::IDLE_WAIT;

use compute::{compute_thread, Done, Work};
use lease_loop::{connect, lease_loop};
use salient_proto::v1;
use signals::Signals;
use std::future::Future;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::mpsc;

/// How the worker runs.
pub struct Options {
    /// URL of the coordinator.
    pub coordinator: String,
    /// Threads integrating orbits.
    pub threads: usize,
    /// Name the worker registers under (shown in the coordinator's logs).
    pub name: String,
    /// Bearer token sent to the coordinator.
    pub token: Option<String>,
    /// PEM of the certificate authority that signed the coordinator's certificate.
    pub tls_ca: Option<Vec<u8>>,
    /// Leases held at once: one in progress and the rest ready, so the pool need not wait on
    /// the network (fast-PSS leases are held one at a time, see `free_slots` in lease_loop.rs).
    pub max_leases: usize,
    /// How long a drain may take: past it the worker stops whatever it still holds (a
    /// coordinator that is gone cannot take its reports; its leases go to others anyway).
    pub drain_timeout: Duration,
}

/// How long a stopping worker waits for the coordinator to take its leave.
const DEREGISTER_TIMEOUT: Duration = Duration::from_secs(2);

/// Runs until `drain` resolves and the held leases are finished or released.
pub async fn run(opts: Options, drain: impl Future<Output = ()>) -> Result<(), String> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.threads)
        .thread_name(|i| format!("salient-worker-{i}"))
        .build()
        .map_err(|e| format!("starting the thread pool: {e}"))?;
    let signals = Arc::new(Mutex::new(Signals::default()));
    let draining = Arc::new(AtomicBool::new(false));
    let (work_tx, work_rx) = std::sync::mpsc::channel::<Work>();
    let (done_tx, mut done_rx) = mpsc::unbounded_channel::<Done>();
    let compute = {
        let (signals, draining) = (signals.clone(), draining.clone());
        std::thread::Builder::new()
            .name("salient-compute".into())
            .spawn(move || compute_thread(pool, work_rx, done_tx, signals, draining))
            .map_err(|e| format!("starting the compute thread: {e}"))?
    };

    let mut client = connect(&opts).await?;
    // The drain signal goes to the lease loop and to the drain deadline both.
    let (drain_tx, drain_rx) = tokio::sync::watch::channel(false);
    let mut reg: Option<v1::RegisterReply> = None;
    let mut held: Vec<v1::TileRef> = Vec::new();
    let mut released: Vec<v1::TileRef> = Vec::new();
    let lease_loop = lease_loop(
        &opts,
        &mut client,
        &mut reg,
        &mut held,
        &mut released,
        (&signals, &draining),
        (&work_tx, &mut done_rx),
        drain_rx,
    );
    let drained_in_time = tokio::select! {
        r = lease_loop => { r?; true }
        _ = async {
            drain.await;
            let _ = drain_tx.send(true);
            tokio::time::sleep(opts.drain_timeout).await;
        } => false,
    };
    drop(work_tx);
    if !drained_in_time {
        tracing::warn!(
            drain_timeout_s = opts.drain_timeout.as_secs_f64(),
            held = held.len(),
            "drain deadline passed; stopping with leases unfinished (the coordinator gives them to others)"
        );
        released.append(&mut held);
    }
    if let Some(reg) = &reg {
        // Bounded: a coordinator that is gone would keep this waiting.
        let _ = tokio::time::timeout(
            DEREGISTER_TIMEOUT,
            client.deregister(v1::DeregisterRequest {
                worker_id: reg.worker_id.clone(),
                released,
            }),
        )
        .await;
    }
    if drained_in_time {
        let _ = tokio::task::spawn_blocking(move || compute.join()).await;
    }
    tracing::info!("worker stopped");
    Ok(())
}
