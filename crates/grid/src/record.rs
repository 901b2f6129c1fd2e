//! Outcomes as bytes for a run's checkpoint: framed records, each a batch of outcomes with
//! its length and checksum, appended one after another. A record cut short by a killed process
//! (or otherwise damaged) fails its checksum, and reading stops before it: what a reader gets
//! is always a prefix of whole batches, every bit as it was committed (f64s by their bits, NaN
//! included).

use crate::ledger::{CellIndicators, Outcome};
use salient_core::orbit::{Class, Status};

// A status's code is its place in `Status::ALL`, a class's its place in `Class::ALL` plus one
// (0: no class).

/// Bytes before a record's payload: its length (u32) and FNV-1a 64 checksum (u64).
const FRAME: usize = 12;

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

fn class_code(c: Option<Class>) -> u8 {
    c.map_or(0, |c| {
        Class::ALL.iter().position(|&k| k == c).unwrap_or(0) as u8 + 1
    })
}

fn class_of(code: u8) -> Option<Option<Class>> {
    match code {
        0 => Some(None),
        k => Class::ALL.get(usize::from(k) - 1).map(|&c| Some(c)),
    }
}

/// One record holding `outcomes`, to append to a checkpoint.
pub fn encode_record(outcomes: &[Outcome]) -> Vec<u8> {
    let mut p = Vec::new();
    for o in outcomes {
        p.extend(o.cell.to_le_bytes());
        p.push(class_code(o.class));
        let status = Status::ALL.iter().position(|&s| s == o.status).unwrap_or(0);
        p.push(status as u8);
        p.extend(o.sali.to_bits().to_le_bytes());
        p.extend(o.steps.to_le_bytes());
        p.extend(o.t_end.to_bits().to_le_bytes());
        p.extend((o.visited.len() as u32).to_le_bytes());
        for v in &o.visited {
            p.extend(v.to_le_bytes());
        }
        p.extend((o.checkpoints.len() as u32).to_le_bytes());
        p.extend(o.checkpoints.iter().map(|&c| class_code(c)));
        match &o.indicators {
            None => p.push(0),
            Some(v) => {
                p.push(1);
                for x in [v.mle, v.megno, v.megno_mean, v.fli] {
                    p.extend(x.to_bits().to_le_bytes());
                }
            }
        }
    }
    let mut out = Vec::with_capacity(FRAME + p.len());
    out.extend((p.len() as u32).to_le_bytes());
    out.extend(fnv1a(&p).to_le_bytes());
    out.extend(p);
    out
}

/// The outcomes of the whole records at the start of `bytes`, in order, and the length of
/// that prefix: a damaged or incomplete record and everything after it are left out.
pub fn decode_records(bytes: &[u8]) -> (Vec<Outcome>, usize) {
    let mut outcomes = Vec::new();
    let mut at = 0;
    while let Some(frame) = bytes.get(at..at + FRAME) {
        let len = u32::from_le_bytes(frame[..4].try_into().expect("4 bytes")) as usize;
        let sum = u64::from_le_bytes(frame[4..].try_into().expect("8 bytes"));
        let Some(payload) = bytes.get(at + FRAME..at + FRAME + len) else {
            break;
        };
        if fnv1a(payload) != sum {
            break;
        }
        match decode_payload(payload) {
            Some(batch) => outcomes.extend(batch),
            None => break,
        }
        at += FRAME + len;
    }
    (outcomes, at)
}

/// Reads little-endian fields off the front of a payload.
struct Reader<'a>(&'a [u8]);

impl Reader<'_> {
    fn take<const N: usize>(&mut self) -> Option<[u8; N]> {
        let (head, rest) = self.0.split_first_chunk::<N>()?;
        self.0 = rest;
        Some(*head)
    }
    fn u8(&mut self) -> Option<u8> {
        self.take::<1>().map(|b| b[0])
    }
    fn u32(&mut self) -> Option<u32> {
        self.take().map(u32::from_le_bytes)
    }
    fn u64(&mut self) -> Option<u64> {
        self.take().map(u64::from_le_bytes)
    }
    fn f64(&mut self) -> Option<f64> {
        self.u64().map(f64::from_bits)
    }
}

fn decode_payload(payload: &[u8]) -> Option<Vec<Outcome>> {
    let mut r = Reader(payload);
    let mut out = Vec::new();
    while !r.0.is_empty() {
        let cell = r.u32()?;
        let class = class_of(r.u8()?)?;
        let status = *Status::ALL.get(usize::from(r.u8()?))?;
        let (sali, steps, t_end) = (r.f64()?, r.u64()?, r.f64()?);
        let n = r.u32()? as usize;
        let visited = (0..n).map(|_| r.u32()).collect::<Option<Vec<_>>>()?;
        let n = r.u32()? as usize;
        let checkpoints = (0..n)
            .map(|_| class_of(r.u8()?))
            .collect::<Option<Vec<_>>>()?;
        let indicators = match r.u8()? {
            0 => None,
            1 => Some(CellIndicators {
                mle: r.f64()?,
                megno: r.f64()?,
                megno_mean: r.f64()?,
                fli: r.f64()?,
            }),
            _ => return None,
        };
        out.push(Outcome {
            cell,
            class,
            status,
            sali,
            visited,
            steps,
            t_end,
            checkpoints,
            indicators,
        });
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Vec<Outcome> {
        vec![
            Outcome {
                cell: 7,
                class: Some(Class::Sticky),
                status: Status::Ok,
                sali: 1.234_567_890_123e-6,
                visited: vec![3, 9, 4_000_000],
                steps: 20_000,
                t_end: 1e4,
                checkpoints: vec![None, Some(Class::Regular), Some(Class::Chaotic)],
                indicators: Some(CellIndicators {
                    mle: 4.5e-4,
                    megno: 2.0125,
                    megno_mean: 1.9,
                    fli: -0.5,
                }),
            },
            Outcome {
                cell: 11,
                class: None,
                status: Status::Escaped,
                sali: f64::NAN,
                visited: Vec::new(),
                steps: 3,
                t_end: 5.5,
                checkpoints: Vec::new(),
                indicators: None,
            },
        ]
    }

    fn same(a: &[Outcome], b: &[Outcome]) -> bool {
        // By bits: NaN SALI included.
        a.len() == b.len()
            && a.iter().zip(b).all(|(x, y)| {
                x.sali.to_bits() == y.sali.to_bits()
                    && Outcome {
                        sali: 0.0,
                        ..x.clone()
                    } == Outcome {
                        sali: 0.0,
                        ..y.clone()
                    }
            })
    }

    #[test]
    fn records_round_trip_bit_for_bit() {
        let all = sample();
        let mut bytes = encode_record(&all[..1]);
        bytes.extend(encode_record(&all[1..]));
        bytes.extend(encode_record(&[]));
        let (back, len) = decode_records(&bytes);
        assert_eq!(len, bytes.len());
        assert!(same(&back, &all), "{back:?}");
    }

    /// A record cut anywhere, or with a byte changed, is left out with what follows it; the
    /// records before it are read whole.
    #[test]
    fn a_cut_or_damaged_record_ends_the_reading() {
        let all = sample();
        let first = encode_record(&all[..1]);
        let mut bytes = first.clone();
        bytes.extend(encode_record(&all[1..]));
        for cut in first.len()..bytes.len() {
            let (back, len) = decode_records(&bytes[..cut]);
            assert_eq!(len, first.len(), "cut at {cut}");
            assert!(same(&back, &all[..1]));
        }
        for at in [first.len() + 3, first.len() + FRAME + 5, bytes.len() - 1] {
            let mut damaged = bytes.clone();
            damaged[at] ^= 0x10;
            let (back, len) = decode_records(&damaged);
            assert_eq!(len, first.len(), "byte {at}");
            assert!(same(&back, &all[..1]));
        }
        assert_eq!(decode_records(&first[..5]).1, 0);
    }
}
