//! What the network side tells the compute side while leases run: cells to skip, leases
//! revoked, each fast-PSS run's own ledger fed with relayed outcomes; and the outcomes of
//! running leases on their way to the next poll.

use salient_grid::executor::LocalLedger;
use salient_grid::spec::JobSpec;
use salient_grid::Grid;
use salient_proto::v1;
use salient_proto::{outcome_from_wire, Expected};
use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};

/// Cells to skip and leases revoked, written by the network side, read by the compute side;
/// and per run its own ledger, fed relayed outcomes by the network side, whose claims a skip
/// abandons an orbit already running through.
#[derive(Default)]
pub(crate) struct Signals {
    /// By lease (job, run, tile, attempt).
    pub(crate) skips: HashMap<LeaseKey, HashSet<u32>>,
    pub(crate) revoked: HashSet<LeaseKey>,
    pub(crate) ledgers: HashMap<(u64, u32), RunLedger>,
    /// Runs this worker has made a ledger of: one made again (the compute side keeps few)
    /// asks for its own outcomes to be relayed too.
    pub(crate) made: HashSet<(u64, u32)>,
    /// Outcomes of leases still running, for the next poll: a report that woke the network
    /// side for every outcome would make a poll (and a store commit) of each, and the
    /// coordinator shares the cores.
    pub(crate) partial: Vec<v1::TileReport>,
    /// Cells running orbits crossed since the last poll, and whether the orbit was abandoned
    /// since, by (lease, orbit's cell).
    pub(crate) crossings: HashMap<(LeaseKey, u32), (Vec<u32>, bool)>,
}

/// A lease as (job, run, tile, attempt).
pub type LeaseKey = (u64, u32, u32, u32);

/// A fast-PSS run's own ledger and how far it got in the coordinator's relayed outcomes (its
/// `RelayMark`): kept together so that a ledger made afresh always starts from the beginning.
pub(crate) struct RunLedger {
    pub(crate) local: Arc<LocalLedger>,
    pub(crate) relayed: u64,
    /// The relay must bring this worker's own outcomes as well: the ledger was made after an
    /// earlier one of the same run was dropped, with the outcomes this worker had offered it.
    /// Without them the ledger's commits stop at the first such cell, its pending outcomes
    /// keep claiming cells the coordinator still leases, and those cells are abandoned at
    /// every lease.
    pub(crate) own: bool,
}

impl Signals {
    /// The run's ledger, made if there is none (on `grid`, or on the spec's grid, built only
    /// then).
    pub(crate) fn ledger(
        &mut self,
        key: (u64, u32),
        spec: &JobSpec,
        grid: Option<&Grid>,
    ) -> &mut RunLedger {
        let again = !self.made.insert(key);
        self.ledgers.entry(key).or_insert_with(|| {
            if again {
                tracing::debug!(
                    job = key.0,
                    run = key.1,
                    "ledger made again; asking for this worker's own outcomes too"
                );
            }
            RunLedger {
                local: Arc::new(match grid {
                    Some(g) => LocalLedger::new(g, spec.mode(key.1 as usize)),
                    None => LocalLedger::new(&spec.grid(key.1 as usize), spec.mode(key.1 as usize)),
                }),
                relayed: 0,
                own: again,
            }
        })
    }
}

/// The key of lease `l`.
pub fn lease_key(l: &v1::TileRef) -> LeaseKey {
    (l.job, l.run, l.tile, l.attempt)
}

/// The crossings of running orbits (by lease and orbit's cell: cells crossed, stopped) as a
/// poll tells them: those of leases still `held`, each with its lease.
pub fn crossings_of_held(
    taken: impl IntoIterator<Item = ((LeaseKey, u32), (Vec<u32>, bool))>,
    held: &[v1::TileRef],
) -> Vec<v1::Crossings> {
    taken
        .into_iter()
        .filter_map(|((key, cell), (crossed, stopped))| {
            let lease = held.iter().find(|h| lease_key(h) == key)?;
            Some(v1::Crossings {
                lease: Some(*lease),
                cell,
                crossed,
                stopped,
            })
        })
        .collect()
}

/// Offers another worker's outcomes, relayed by the coordinator, to the run's own ledger; one
/// that does not fit the grid is logged and left out (the relay is advice, never a reason to
/// stop).
pub(crate) fn apply_relay(local: &LocalLedger, relay: &v1::Relay) {
    for encoded in &relay.outcomes {
        let checked = <v1::Outcome as prost::Message>::decode(&encoded[..])
            .map_err(|e| e.to_string())
            .and_then(|o| outcome_from_wire(&o, local.grid(), Expected::as_sent(&o)));
        match checked {
            Ok(o) => local.offer(o),
            Err(e) => {
                tracing::warn!(job = relay.job, run = relay.run, error = %e, "relayed outcome left out");
            }
        }
    }
}

/// Moves the outcomes of running leases into the outbox (those of leases still held).
pub(crate) fn collect_partial(
    signals: &Mutex<Signals>,
    held: &[v1::TileRef],
    outbox: &mut Vec<v1::TileReport>,
) {
    let partial = std::mem::take(&mut signals.lock().expect("signals").partial);
    outbox.extend(
        partial
            .into_iter()
            .filter(|r| held.iter().any(|h| Some(h) == r.lease.as_ref())),
    );
}
