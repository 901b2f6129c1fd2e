//! The network side: registers with the coordinator, then polls — heartbeat, renewals,
//! reports, requests for leases — hands the leases that come to the compute thread, and applies
//! what each reply says: answers to reports, skips, revokes, relayed outcomes.

use crate::compute::{Done, Work};
use crate::signals::{apply_relay, collect_partial, crossings_of_held, lease_key, Signals};
use crate::Options;
use salient_grid::spec::{self, JobSpec};
use salient_proto::v1;
use salient_proto::v1::worker_service_client::WorkerServiceClient;
use salient_proto::{endpoint, explain_transport, Token, MAX_MESSAGE_BYTES, PROTOCOL_VERSION};
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;
use tonic::{Code, Status};

type Client = WorkerServiceClient<InterceptedService<Channel, Token>>;

pub(crate) async fn connect(opts: &Options) -> Result<Client, String> {
    let channel = endpoint(&opts.coordinator, opts.tls_ca.as_deref())?.connect_lazy();
    Ok(
        WorkerServiceClient::with_interceptor(channel, Token(opts.token.clone()))
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES),
    )
}

/// Registers, retrying with backoff while the coordinator is away. Refusals (wrong protocol
/// version, bad token) end the worker.
async fn register(client: &mut Client, opts: &Options) -> Result<v1::RegisterReply, String> {
    let mut backoff = Duration::from_millis(100);
    loop {
        let req = v1::RegisterRequest {
            protocol_version: PROTOCOL_VERSION,
            name: opts.name.clone(),
            threads: opts.threads as u32,
        };
        match client.register(req).await {
            Ok(r) => {
                let r = r.into_inner();
                tracing::info!(worker = %r.worker_id, coordinator = %opts.coordinator, "registered");
                return Ok(r);
            }
            Err(e)
                if matches!(
                    e.code(),
                    Code::Unavailable | Code::Unknown | Code::Cancelled | Code::DeadlineExceeded
                ) =>
            {
                tracing::warn!(coordinator = %opts.coordinator, error = %explain_transport(&opts.coordinator, &e), retry_in_ms = backoff.as_millis() as u64, "coordinator unreachable");
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(Duration::from_secs(5));
            }
            Err(e) => {
                return Err(format!(
                    "the coordinator refused this worker: {}",
                    e.message()
                ))
            }
        }
    }
}

/// Leases to ask for: up to `max` held, but one at a time while the last lease was fast PSS
/// (and before any lease came), and [`HUNGRY_LEASES`] more whenever the compute side is
/// `hungry` (a lane idle with no leased cell waiting; the leases held then are only finishing
/// their orbits). A fast-PSS lease is the next cells the coordinator's ledger needs; one asked
/// for before a lane is free would take cells before the outcomes that may label them arrive,
/// and is slower (figures: docs/performance.md). Full-mode tiles carry no such risk, and a
/// second one keeps the threads busy across the round trip.
pub fn free_slots(held: usize, hungry: bool, one_at_a_time: bool, max: usize) -> usize {
    let cap = if one_at_a_time { 1 } else { max };
    let hungry = if hungry { HUNGRY_LEASES } else { 0 };
    cap.saturating_sub(held).max(hungry)
}

/// Leases a hungry compute side asks for at once. A fast-PSS lease holds the wanted cells of
/// one tile, often only a few of the batch it may hold, and every poll that carries reports
/// waits for the coordinator's fsync while the lanes run dry. Two beat one; three drop more
/// and are no faster (figures: docs/performance.md).
pub const HUNGRY_LEASES: usize = 2;

/// Reports sent in one poll at most (bytes); the rest go in the next, well below the
/// coordinator's message limit.
const POLL_REPORT_BYTES: usize = 4 << 20;

/// How long a sent report may wait for its answer before it is sent again. Answers come with
/// the next poll after the coordinator's commit, milliseconds later; one missing this long
/// was lost with a coordinator that stopped before committing it (a restart is caught
/// sooner, by its NOT_FOUND).
const UNANSWERED_RESEND: Duration = Duration::from_secs(10);

/// Registers, then polls for leases, hands them to the compute thread and reports what it
/// computes, until the drain signal came and nothing is held or owed any more.
#[allow(clippy::too_many_arguments)]
pub(crate) async fn lease_loop(
    opts: &Options,
    client: &mut Client,
    reg_slot: &mut Option<v1::RegisterReply>,
    held: &mut Vec<v1::TileRef>,
    released: &mut Vec<v1::TileRef>,
    (signals, draining): (&Arc<Mutex<Signals>>, &Arc<AtomicBool>),
    (work_tx, done_rx): (
        &std::sync::mpsc::Sender<Work>,
        &mut mpsc::UnboundedReceiver<Done>,
    ),
    mut drain_rx: tokio::sync::watch::Receiver<bool>,
) -> Result<(), String> {
    let reg = register(client, opts).await?;
    *reg_slot = Some(reg.clone());
    let mut poller = Poller {
        opts,
        client,
        reg_slot,
        reg,
        held,
        released,
        signals,
        draining,
        work_tx,
        specs: HashMap::new(),
        one_at_a_time: true,
        hungry_compute: false,
        outbox: Vec::new(),
        awaiting: VecDeque::new(),
        backoff: Duration::from_millis(100),
        hungry_wait: Duration::from_millis(2),
    };
    let mut drain_seen = false;
    loop {
        let idle = poller.idle_wait();
        tokio::select! {
            _ = drain_rx.wait_for(|&d| d), if !drain_seen => {
                drain_seen = true;
                poller.draining.store(true, Ordering::Relaxed);
                tracing::info!(held = poller.held.len(), "draining: finishing the lease in progress, releasing the rest");
            }
            d = done_rx.recv() => {
                let Some(d) = d else { return Err("the compute thread stopped".into()) };
                poller.take_done(d, done_rx);
            }
            _ = tokio::time::sleep(idle) => {}
        }
        let draining_now = poller.draining.load(Ordering::Relaxed);
        if draining_now && poller.owes_nothing() {
            return Ok(());
        }
        poller.poll(draining_now).await?;
    }
}

/// The lease loop's state between polls, and the worker's state it shares with [`crate::run`]
/// (the registration, the leases held, the leases released).
struct Poller<'a> {
    opts: &'a Options,
    client: &'a mut Client,
    reg_slot: &'a mut Option<v1::RegisterReply>,
    reg: v1::RegisterReply,
    held: &'a mut Vec<v1::TileRef>,
    released: &'a mut Vec<v1::TileRef>,
    signals: &'a Mutex<Signals>,
    draining: &'a AtomicBool,
    work_tx: &'a std::sync::mpsc::Sender<Work>,
    /// Each job's spec, with the text it was parsed from.
    specs: HashMap<u64, (String, Arc<JobSpec>)>,
    /// The last lease was fast PSS (or none came yet): see [`free_slots`].
    one_at_a_time: bool,
    /// The compute side said [`Done::Hungry`] since the last lease came.
    hungry_compute: bool,
    /// Reports not sent yet.
    outbox: Vec<v1::TileReport>,
    /// Reports sent and not yet answered, in the order sent. The coordinator answers a poll
    /// before committing what it carried, so the answers to its reports come with a later
    /// reply, in the order the reports came: each answer for a lease is the answer to the
    /// oldest report of that lease waiting here.
    awaiting: VecDeque<(Instant, v1::TileReport)>,
    /// The wait before the next poll after a failed one.
    backoff: Duration,
    /// A worker with free slots and nothing leased polls soon again (the frontier moves as
    /// others report), backing off to the coordinator's interval while nothing comes.
    hungry_wait: Duration,
}

impl Poller<'_> {
    /// The coordinator's poll interval, kept within 10 ms and 5 s.
    fn poll_interval(&self) -> Duration {
        Duration::from_millis(self.reg.poll_ms.clamp(10, 5000) as u64)
    }

    /// How long to wait for the compute side before the next poll.
    fn idle_wait(&self) -> Duration {
        let busy = self.poll_interval();
        if !self.outbox.is_empty() {
            // Reports left over from a poll that carried its byte budget.
            Duration::ZERO
        } else if free_slots(
            self.held.len(),
            self.hungry_compute,
            self.one_at_a_time,
            self.opts.max_leases,
        ) > 0
            && !self.draining.load(Ordering::Relaxed)
        {
            self.hungry_wait.min(busy)
        } else {
            busy
        }
    }

    /// Takes what the compute side sent: `first`, and whatever else already waits in `done_rx`.
    fn take_done(&mut self, first: Done, done_rx: &mut mpsc::UnboundedReceiver<Done>) {
        let mut next = Some(first);
        while let Some(d) = next.take().or_else(|| done_rx.try_recv().ok()) {
            match d {
                Done::Report(r) => {
                    collect_partial(self.signals, self.held, &mut self.outbox);
                    // Reports of leases revoked or forgotten meanwhile are stale.
                    if !self.held.iter().any(|h| Some(h) == r.lease.as_ref()) {
                        continue;
                    }
                    if r.finished {
                        self.held.retain(|h| Some(h) != r.lease.as_ref());
                    }
                    self.outbox.push(r);
                }
                Done::Released(l) => {
                    self.held.retain(|h| *h != l);
                    self.released.push(l);
                }
                Done::Hungry => self.hungry_compute = true,
            }
        }
    }

    /// Nothing is held, and every report went out and was answered.
    fn owes_nothing(&self) -> bool {
        self.held.is_empty() && self.outbox.is_empty() && self.awaiting.is_empty()
    }

    /// Sends one poll and applies its reply, or what its failure means.
    async fn poll(&mut self, draining_now: bool) -> Result<(), String> {
        let now = Instant::now();
        self.resend_unanswered(now);
        collect_partial(self.signals, self.held, &mut self.outbox);
        let req = self.poll_request(draining_now);
        // The first `sent` of the outbox go with this poll and wait for their answers.
        let sent = req.reports.len();
        self.awaiting
            .extend(self.outbox.drain(..sent).map(|r| (now, r)));
        match self.client.poll(req).await {
            Ok(reply) => self.apply_reply(reply.into_inner()),
            Err(e) => self.poll_failed(e, sent).await,
        }
    }

    /// Answers are normally one poll behind; ones missing for long were lost (a coordinator
    /// that failed before committing them): send those reports again.
    fn resend_unanswered(&mut self, now: Instant) {
        while self
            .awaiting
            .front()
            .is_some_and(|(at, _)| now.duration_since(*at) > UNANSWERED_RESEND)
        {
            let (_, r) = self.awaiting.pop_front().expect("checked");
            tracing::warn!(lease = ?r.lease, "report not acknowledged; resending");
            self.outbox.insert(0, r);
        }
    }

    /// The heartbeat: the leases held, how many more to lease (none while draining), the
    /// reports that fit one poll, and how far each run's relay came.
    fn poll_request(&self, draining_now: bool) -> v1::PollRequest {
        v1::PollRequest {
            worker_id: self.reg.worker_id.clone(),
            free_slots: if draining_now {
                0
            } else {
                free_slots(
                    self.held.len(),
                    self.hungry_compute,
                    self.one_at_a_time,
                    self.opts.max_leases,
                ) as u32
            },
            held: self.held.clone(),
            reports: {
                // At least one report, then as many as fit the budget.
                let mut bytes = 0;
                self.outbox
                    .iter()
                    .take_while(|r| {
                        let first = bytes == 0;
                        bytes += prost::Message::encoded_len(*r);
                        first || bytes <= POLL_REPORT_BYTES
                    })
                    .cloned()
                    .collect::<Vec<_>>()
            },
            draining: draining_now,
            crossings: self.crossings(),
            relayed: self
                .signals
                .lock()
                .expect("signals")
                .ledgers
                .iter()
                .map(|(&(job, run), r)| v1::RelayMark {
                    job,
                    run,
                    next: r.relayed,
                    own: r.own,
                })
                .collect(),
        }
    }

    /// The crossings of running orbits of held leases since the last poll.
    fn crossings(&self) -> Vec<v1::Crossings> {
        let taken = std::mem::take(&mut self.signals.lock().expect("signals").crossings);
        crossings_of_held(taken, self.held)
    }

    /// A successful poll's reply: answers to reports, skips and revokes, new leases, relays.
    fn apply_reply(&mut self, reply: v1::PollReply) -> Result<(), String> {
        self.backoff = Duration::from_millis(100);
        self.take_answers(&reply.acknowledged, &reply.stale);
        self.apply_skips_and_revokes(reply.skips, &reply.revoked);
        self.hungry_wait = if reply.leases.is_empty() {
            (self.hungry_wait * 2).min(self.poll_interval())
        } else {
            Duration::from_millis(2)
        };
        self.take_leases(reply.leases)?;
        self.apply_relays(&reply.relays);
        Ok(())
    }

    /// Reports answered (acknowledged, or stale) wait no more.
    fn take_answers(&mut self, acknowledged: &[v1::TileRef], stale: &[v1::TileRef]) {
        for answered in acknowledged.iter().chain(stale) {
            let key = lease_key(answered);
            match self
                .awaiting
                .iter()
                .position(|(_, r)| r.lease.as_ref().map(lease_key) == Some(key))
            {
                Some(k) => drop(self.awaiting.remove(k)),
                None => tracing::debug!(lease = %answered, "answer to no report waiting"),
            }
        }
    }

    /// Skips and revokes go to the compute side; revoked leases are no longer held, nor their
    /// reports sent.
    fn apply_skips_and_revokes(&mut self, skips: Vec<v1::Skip>, revoked: &[v1::TileRef]) {
        {
            let mut s = self.signals.lock().expect("signals");
            for skip in skips {
                if let Some(l) = skip.lease {
                    if let Some(r) = s.ledgers.get(&(l.job, l.run)) {
                        let claims = r.local.claims();
                        skip.cells.iter().for_each(|&cell| claims.claim(cell));
                    }
                    s.skips
                        .entry((l.job, l.run, l.tile, l.attempt))
                        .or_default()
                        .extend(skip.cells);
                }
            }
            for r in revoked {
                s.revoked.insert((r.job, r.run, r.tile, r.attempt));
            }
        }

        for r in revoked {
            tracing::info!(lease = %r, "lease revoked");
            self.held.retain(|h| h != r);
            self.outbox.retain(|o| o.lease.as_ref() != Some(r));
        }
    }

    /// Holds the new leases and hands them to the compute thread.
    fn take_leases(&mut self, leases: Vec<v1::Lease>) -> Result<(), String> {
        for lease in leases {
            let Some(tile) = lease.lease else { continue };
            let Some(spec) = self.spec_of(&tile, &lease.spec_json) else {
                continue;
            };
            tracing::debug!(lease = %tile, cells = lease.cells.len(), "leased");
            let mode = spec.mode(tile.run as usize);
            if mode == salient_grid::Mode::FastPss {
                // Made here, not by the compute side, so that the outcomes relayed in
                // this reply find it.
                self.signals
                    .lock()
                    .expect("signals")
                    .ledger((tile.job, tile.run), &spec, None);
            }
            self.one_at_a_time = mode == salient_grid::Mode::FastPss;
            self.hungry_compute = false;
            self.held.push(tile);
            if self
                .work_tx
                .send(Work {
                    lease: tile,
                    spec,
                    cells: lease.cells,
                })
                .is_err()
            {
                return Err("the compute thread stopped".into());
            }
        }
        Ok(())
    }

    /// The spec of the lease's job: the one read before when the lease carries the same text,
    /// else read now; none (logged) when it cannot be read.
    fn spec_of(&mut self, tile: &v1::TileRef, spec_json: &str) -> Option<Arc<JobSpec>> {
        match self.specs.get(&tile.job) {
            Some((text, s)) if *text == spec_json => Some(s.clone()),
            _ => match spec::parse(spec_json, true) {
                Ok(s) => {
                    let s = Arc::new(s);
                    if self.specs.len() >= 16 {
                        let held = &self.held;
                        self.specs
                            .retain(|job, _| held.iter().any(|h| h.job == *job));
                    }
                    self.specs
                        .insert(tile.job, (spec_json.to_string(), s.clone()));
                    Some(s)
                }
                Err(e) => {
                    tracing::error!(job = tile.job, error = %e, "cannot read the job's spec; not taking the lease (the coordinator gets it back at the next poll)");
                    None
                }
            },
        }
    }

    /// Other workers' outcomes, relayed, go to their runs' ledgers.
    fn apply_relays(&self, relays: &[v1::Relay]) {
        if !relays.is_empty() {
            let mut s = self.signals.lock().expect("signals");
            for relay in relays {
                if let Some(r) = s.ledgers.get_mut(&(relay.job, relay.run)) {
                    apply_relay(&r.local, relay);
                    r.relayed = relay.next;
                }
            }
        }
    }

    /// A failed poll: a coordinator that forgot this worker is registered with again, refused
    /// reports are dropped, refusals end the worker, and anything else is retried with backoff.
    async fn poll_failed(&mut self, e: Status, sent: usize) -> Result<(), String> {
        match e.code() {
            Code::NotFound => {
                // The coordinator restarted and forgot us: register again, keep the outbox
                // and the leases; the next poll resends and re-adopts them.
                tracing::warn!(error = %e.message(), "coordinator does not know this worker");
                self.register_again().await?;
            }
            Code::InvalidArgument if sent > 0 => {
                // The coordinator refuses what this poll carried (it changed nothing): drop
                // those reports rather than resend them forever; their tiles are leased again.
                tracing::error!(error = %e.message(), dropped_reports = sent, "the coordinator refused reports; dropping them");
                self.awaiting
                    .truncate(self.awaiting.len().saturating_sub(sent));
            }
            Code::Unauthenticated | Code::FailedPrecondition | Code::InvalidArgument => {
                return Err(format!("the coordinator refused a poll: {}", e.message()));
            }
            _ => {
                // Perhaps applied, perhaps not: this poll's reports go again (a repeat
                // changes nothing); their answers, if owed, come all the same.
                for _ in 0..sent {
                    if let Some((_, r)) = self.awaiting.pop_back() {
                        self.outbox.insert(0, r);
                    }
                }
                tracing::warn!(error = %e.message(), retry_in_ms = self.backoff.as_millis() as u64, pending_reports = self.outbox.len(), "poll failed");
                tokio::time::sleep(self.backoff).await;
                self.backoff = (self.backoff * 2).min(Duration::from_secs(5));
            }
        }
        Ok(())
    }

    /// Registers with a restarted coordinator, keeping the outbox and the leases unless it
    /// runs on another store.
    async fn register_again(&mut self) -> Result<(), String> {
        let again = register(self.client, self.opts).await?;
        // What it had not committed is gone with it: everything unanswered goes again.
        for (_, r) in self.awaiting.drain(..).rev() {
            self.outbox.insert(0, r);
        }
        // The marks counted the old process's relays.
        for r in self.signals.lock().expect("signals").ledgers.values_mut() {
            r.relayed = 0;
        }
        if again.coordinator_id != self.reg.coordinator_id {
            // Another store: its job ids, tiles and attempts are not the ones we hold.
            tracing::warn!(
                dropped_reports = self.outbox.len(),
                dropped_leases = self.held.len(),
                "the coordinator runs on another store; forgetting jobs, leases and reports"
            );
            let mut s = self.signals.lock().expect("signals");
            for h in self.held.drain(..) {
                s.revoked.insert((h.job, h.run, h.tile, h.attempt));
            }
            self.outbox.clear();
            self.specs.clear();
            s.ledgers.clear();
            s.made.clear();
        }
        *self.reg_slot = Some(again.clone());
        self.reg = again;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_pss_leases_are_held_one_at_a_time() {
        // Fast PSS (and before any lease): one at a time, whatever --leases says.
        assert_eq!(free_slots(0, false, true, 4), 1);
        assert_eq!(free_slots(1, false, true, 4), 0);
        // Full mode: up to --leases.
        assert_eq!(free_slots(0, false, false, 4), 4);
        assert_eq!(free_slots(3, false, false, 4), 1);
        assert_eq!(free_slots(5, false, false, 4), 0);
        // A hungry compute side gets more, whatever is held.
        assert_eq!(free_slots(1, true, true, 4), HUNGRY_LEASES);
        assert_eq!(free_slots(5, true, false, 4), HUNGRY_LEASES);
        assert_eq!(free_slots(0, true, false, 4), 4);
    }
}
