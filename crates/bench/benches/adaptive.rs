//! ns per step of the adaptive integrators on R1 with 2 deviation vectors (12 ODEs), natural
//! steps, and ns per right-hand-side evaluation (DOP853 makes 12 per accepted step). The
//! `polynomial` cases run Hénon–Heiles given as text through the polynomial path.

use salient_bench::Harness;
use salient_core::adaptive::dop853::{rhs, Dop853, Dop853Config};
use salient_core::adaptive::taylor::Taylor;
use salient_core::arith::dd::DoubleDouble;
use salient_core::orbit::initial_vectors;
use salient_core::phase::Phase;
use salient_core::section::on_section;
use salient_core::systems::polynomial::{Polynomial, PolynomialSystem};
use salient_core::systems::series::TaylorSeries;
use salient_core::{Deviation, HenonHeiles};
use std::hint::black_box;

const STEPS: u64 = 1000;

fn r1() -> Phase<f64, 2, 2> {
    let (q, p) = on_section(&HenonHeiles, 0.125, &[0.558], &[0.0]).unwrap();
    let (dq, dp) = initial_vectors::<2, 2>(Deviation::Axes);
    Phase { q, p, dq, dp }
}

fn main() {
    let h = Harness::from_args();
    let text =
        PolynomialSystem::new(Polynomial::parse("(q1^2 + q2^2)/2 + q1^2*q2 - q2^3/3", 2).unwrap());
    system(&h, &HenonHeiles, "");
    system(&h, &text, "/polynomial");
}

fn system<H: TaylorSeries<2>>(h: &Harness, ham: &H, label: &str) {
    h.case(
        &format!("adaptive/rhs-evaluation{label}"),
        1,
        "evaluation",
        || rhs(ham, black_box(&r1())),
    );
    for delta in [1e-10, 1e-13] {
        h.case(
            &format!("adaptive/dop853-step/{delta:e}{label}"),
            STEPS,
            "step",
            || {
                let mut d = Dop853::new(ham, Dop853Config::with_delta(delta), 0.0, r1());
                for _ in 0..STEPS {
                    d.step(f64::INFINITY, None).unwrap();
                }
                d.evaluations
            },
        );
    }
    for delta in [1e-10, 1e-15] {
        h.case(
            &format!("adaptive/taylor-step/{delta:e}{label}"),
            STEPS,
            "step",
            || {
                let mut t = Taylor::new(ham, delta, 0.0, r1());
                for _ in 0..STEPS {
                    t.step(f64::INFINITY).unwrap();
                }
                t.t()
            },
        );
    }
    let y = r1();
    let dd = Phase {
        q: y.q.map(DoubleDouble::from_f64),
        p: y.p.map(DoubleDouble::from_f64),
        dq: y.dq.map(|v| v.map(DoubleDouble::from_f64)),
        dp: y.dp.map(|v| v.map(DoubleDouble::from_f64)),
    };
    h.case(
        &format!("adaptive/taylor-dd-step/1e-28{label}"),
        100,
        "step",
        || {
            let mut t = Taylor::new(ham, 1e-28, 0.0, dd);
            for _ in 0..100 {
                t.step(f64::INFINITY).unwrap();
            }
            t.t()
        },
    );
}
