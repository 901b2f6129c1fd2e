//! Symplectic splitting schemes for H = A + B, A = ½|p|² (drift), B = V(q) (kick), as data.
//!
//! Every scheme here is palindromic and is stored as the first half of its sequence up to and
//! including the middle element; [`Scheme::ops`] mirrors it. A scheme with Laskar & Robutel's
//! corrector C gets C = exp(−(g/2)τ³ L_K), K = |∇V|², at both ends: p ← p + (gτ³/2)∇K. Since C
//! and a kick both move p by a function of q, the corrector is folded into the end kicks of SBAB
//! schemes and stands alone (a kick with b = 0) at the ends of SABA schemes.
//!
//! Coefficients and orders: Laskar & Robutel 2001 for SABA_n, SBAB_n and their correctors;
//! Blanes et al. 2013 for ABA864; Blanes & Moan 2002 for SRKN^a_14.

// Coefficients keep the digits their sources publish; f64 rounds them once.
#![allow(clippy::excessive_precision)]

/// One sub-map of a splitting step, with coefficients as fractions of the step τ.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Op {
    /// q ← q + aτ p.
    Drift(f64),
    /// p ← p − bτ ∇V(q) + γτ³ ∇K(q), K = |∇V|² (γ = g/2 for a corrector, 0 for a plain kick).
    Kick {
        /// Coefficient b of the kick.
        b: f64,
        /// Coefficient γ of the corrector term.
        gamma: f64,
    },
}

/// Which sub-map a scheme's sequence starts (and, being palindromic, ends) with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum First {
    /// Starts with a drift.
    Drift,
    /// Starts with a kick.
    Kick,
}

/// A palindromic splitting scheme.
#[derive(Clone, Debug, PartialEq)]
pub struct Scheme {
    /// The CLI name without the `tm-` prefix (`sbab2c`).
    pub name: &'static str,
    /// Order on H = ½|p|² + V(q) (no small parameter): 2 for SABA_n/SBAB_n, 4 with corrector
    /// (n ≥ 2), 4 for ABA864, 6 for SRKN14a.
    pub order: u32,
    first: First,
    half: &'static [f64],
    /// Corrector coefficient g (0: no corrector).
    pub corrector: f64,
}

// SABA_n: drifts c_i at Gauss–Legendre spacings, kicks d_i = Gauss weights.
const SABA1: &[f64] = &[0.5, 1.0];
const SABA2: &[f64] = &[
    0.211_324_865_405_187_117_75,
    0.5,
    0.577_350_269_189_625_764_51,
];
const SABA3: &[f64] = &[
    0.112_701_665_379_258_311_48,
    0.277_777_777_777_777_777_78,
    0.387_298_334_620_741_688_52,
    0.444_444_444_444_444_444_44,
];
const SABA4: &[f64] = &[
    0.069_431_844_202_973_712_388,
    0.173_927_422_568_726_928_69,
    0.260_577_634_004_598_155_21,
    0.326_072_577_431_273_071_31,
    0.339_981_043_584_856_264_80,
];
// SBAB_n: kicks d_i = Gauss–Lobatto weights, drifts between Lobatto nodes.
const SBAB1: &[f64] = &[0.5, 1.0];
const SBAB2: &[f64] = &[1.0 / 6.0, 0.5, 2.0 / 3.0];
const SBAB3: &[f64] = &[
    1.0 / 12.0,
    0.276_393_202_250_021_030_36,
    5.0 / 12.0,
    0.447_213_595_499_957_939_28,
];
const SBAB4: &[f64] = &[
    1.0 / 20.0,
    0.172_673_164_646_011_428_10,
    49.0 / 180.0,
    0.327_326_835_353_988_571_90,
    16.0 / 45.0,
];
// Corrector coefficients g (Laskar & Robutel).
const G_SABA1: f64 = 1.0 / 12.0;
const G_SABA2: f64 = 0.011_164_549_684_630_112_770;
const G_SABA3: f64 = 0.005_634_593_363_122_809_402_3;
const G_SABA4: f64 = 0.003_396_775_048_208_601_331_5;
const G_SBAB1: f64 = -1.0 / 24.0;
const G_SBAB2: f64 = 1.0 / 72.0;
const G_SBAB3: f64 = 0.006_318_264_279_517_539_992_9;
const G_SBAB4: f64 = 0.003_644_793_600_153_249_302_3;
// ABA864 (Blanes et al. 2013): a1 b1 a2 b2 a3 b3 a4 b4 | mirror.
const ABA864: &[f64] = &[
    0.071_133_426_498_223_117_777_938_730_006_154_996_417_4,
    0.183_083_687_472_197_221_961_703_757_166_430_291_072,
    0.241_153_427_956_640_098_736_487_795_326_289_649_618,
    0.310_782_859_898_574_869_507_522_291_054_262_796_375,
    0.521_411_761_772_814_789_212_136_078_067_994_229_991,
    -0.026_564_618_511_958_800_697_212_137_916_498_759_266_3,
    -0.333_698_616_227_678_005_726_562_603_400_438_876_027,
    0.065_396_142_282_373_418_455_972_179_391_113_436_371_0,
];
// SRKN^a_14 (Blanes & Moan 2002): a1 b1 … a7 b7 a8 | mirror. The source gives 17 digits;
// b7 and a8 are recomputed from Σa = Σb = 1 in `Scheme::ops` so the sums hold to rounding.
const SRKN14A: &[f64] = &[
    0.037_859_319_840_611_600,
    0.091_719_152_624_461_650,
    0.102_635_633_102_435_00,
    0.183_983_170_005_006_00,
    -0.025_867_888_266_558_700,
    -0.056_534_365_832_888_270,
    0.314_241_403_071_447_00,
    0.004_914_688_774_712_854_0,
    -0.130_144_459_517_415_00,
    0.143_761_127_168_358_00,
    0.106_417_700_369_543_00,
    0.328_567_693_746_804_00,
    -0.008_794_243_128_510_580_0,
    -0.196_411_466_486_454_23,
    0.207_305_069_056_895_4,
];

impl Scheme {
    /// Every scheme Salient knows, in the order the CLI lists them.
    pub fn all() -> Vec<Scheme> {
        let mut v = Vec::new();
        // name, corrected name, first sub-map, half sequence, g, order, corrected order
        type Family = (
            &'static str,
            &'static str,
            First,
            &'static [f64],
            f64,
            u32,
            u32,
        );
        let table: [Family; 8] = [
            ("saba1", "saba1c", First::Drift, SABA1, G_SABA1, 2, 2),
            ("saba2", "saba2c", First::Drift, SABA2, G_SABA2, 2, 4),
            ("saba3", "saba3c", First::Drift, SABA3, G_SABA3, 2, 4),
            ("saba4", "saba4c", First::Drift, SABA4, G_SABA4, 2, 4),
            ("sbab1", "sbab1c", First::Kick, SBAB1, G_SBAB1, 2, 2),
            ("sbab2", "sbab2c", First::Kick, SBAB2, G_SBAB2, 2, 4),
            ("sbab3", "sbab3c", First::Kick, SBAB3, G_SBAB3, 2, 4),
            ("sbab4", "sbab4c", First::Kick, SBAB4, G_SBAB4, 2, 4),
        ];
        for (name, cname, first, half, g, order, corder) in table {
            v.push(Scheme {
                name,
                order,
                first,
                half,
                corrector: 0.0,
            });
            v.push(Scheme {
                name: cname,
                order: corder,
                first,
                half,
                corrector: g,
            });
        }
        v.push(Scheme {
            name: "aba864",
            order: 4,
            first: First::Drift,
            half: ABA864,
            corrector: 0.0,
        });
        v.push(Scheme {
            name: "srkn14a",
            order: 6,
            first: First::Drift,
            half: SRKN14A,
            corrector: 0.0,
        });
        v
    }

    /// Looks a scheme up by its name without the `tm-` prefix.
    pub fn by_name(name: &str) -> Option<Scheme> {
        Scheme::all().into_iter().find(|s| s.name == name)
    }

    /// The same scheme with another corrector coefficient; tests use it to show that a wrong
    /// corrector sign is caught.
    pub fn with_corrector(&self, g: f64) -> Scheme {
        Scheme {
            corrector: g,
            ..self.clone()
        }
    }

    /// Which sub-map the sequence starts with.
    pub fn first(&self) -> First {
        self.first
    }

    /// The full palindromic sequence of sub-maps of one step, correctors included.
    pub fn ops(&self) -> Vec<Op> {
        let mut half = self.half.to_vec();
        if self.name == "srkn14a" {
            // Restore Σa = Σb = 1 exactly from the 17-digit source values.
            let n = half.len();
            let sum_b: f64 = half.iter().skip(1).step_by(2).take(6).sum();
            half[n - 2] = 0.5 - sum_b;
            let sum_a: f64 = half.iter().step_by(2).take(7).sum();
            half[n - 1] = 1.0 - 2.0 * sum_a;
        }
        let mut coeffs = half.clone();
        coeffs.extend(half.iter().rev().skip(1));
        let mut ops: Vec<Op> = coeffs
            .iter()
            .enumerate()
            .map(|(i, &c)| {
                let is_drift = (i % 2 == 0) == (self.first == First::Drift);
                if is_drift {
                    Op::Drift(c)
                } else {
                    Op::Kick { b: c, gamma: 0.0 }
                }
            })
            .collect();
        if self.corrector != 0.0 {
            let gamma = self.corrector / 2.0;
            match self.first {
                First::Kick => {
                    for end in [0, ops.len() - 1] {
                        if let Op::Kick { gamma: gm, .. } = &mut ops[end] {
                            *gm = gamma;
                        }
                    }
                }
                First::Drift => {
                    ops.insert(0, Op::Kick { b: 0.0, gamma });
                    ops.push(Op::Kick { b: 0.0, gamma });
                }
            }
        }
        ops
    }

    /// Force evaluations per step once the two end sub-maps of consecutive steps are merged.
    pub fn kicks_per_step(&self) -> usize {
        let ops = self.ops();
        ops.iter().filter(|o| matches!(o, Op::Kick { .. })).count()
            - usize::from(matches!(ops[0], Op::Kick { .. }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_scheme_is_consistent_palindromic_and_sums_to_one() {
        for s in Scheme::all() {
            let ops = s.ops();
            let n = ops.len();
            for i in 0..n {
                assert_eq!(ops[i], ops[n - 1 - i], "{} not palindromic", s.name);
            }
            let (mut a, mut b) = (0.0, 0.0);
            for op in &ops {
                match *op {
                    Op::Drift(c) => a += c,
                    Op::Kick { b: d, .. } => b += d,
                }
            }
            assert!((a - 1.0).abs() < 1e-15, "{}: Σa = {a}", s.name);
            assert!((b - 1.0).abs() < 1e-15, "{}: Σb = {b}", s.name);
            // Drifts and kicks alternate (a lone corrector counts as a kick with b = 0).
            for w in ops.windows(2) {
                assert_ne!(
                    matches!(w[0], Op::Drift(_)),
                    matches!(w[1], Op::Drift(_)),
                    "{}",
                    s.name
                );
            }
        }
        assert_eq!(Scheme::all().len(), 18);
    }

    #[test]
    fn coefficients_equal_their_closed_forms() {
        let r3 = 3f64.sqrt();
        let r15 = 15f64.sqrt();
        let r5 = 5f64.sqrt();
        let r21 = 21f64.sqrt();
        let r30 = 30f64.sqrt();
        let close = |x: f64, y: f64| (x - y).abs() < 2e-16;
        assert!(close(SABA2[0], 0.5 - r3 / 6.0) && close(SABA2[2], r3 / 3.0));
        assert!(close(SABA3[0], 0.5 - r15 / 10.0) && close(SABA3[2], r15 / 10.0));
        let (sp, sm) = ((525.0 + 70.0 * r30).sqrt(), (525.0 - 70.0 * r30).sqrt());
        assert!(close(SABA4[0], 0.5 - sp / 70.0));
        assert!(close(SABA4[2], (sp - sm) / 70.0));
        assert!(close(SABA4[4], sm / 35.0));
        assert!(close(SABA4[1], 0.25 - r30 / 72.0) && close(SABA4[3], 0.25 + r30 / 72.0));
        assert!(close(SBAB3[1], 0.5 - r5 / 10.0) && close(SBAB3[3], r5 / 5.0));
        assert!(close(SBAB4[1], 0.5 - r21 / 14.0) && close(SBAB4[3], r21 / 14.0));
        assert!(close(G_SABA2, (2.0 - r3) / 24.0));
        assert!(close(G_SABA3, (54.0 - 13.0 * r15) / 648.0));
        assert!(close(G_SBAB3, (13.0 - 5.0 * r5) / 288.0));
        assert!(close(G_SBAB4, 143.0 / 2400.0 - 791.0 * r21 / 64800.0));
    }

    #[test]
    fn sbab2c_is_the_seed_papers_sequence() {
        let ops = Scheme::by_name("sbab2c").unwrap().ops();
        let g = 1.0 / 144.0;
        assert_eq!(
            ops,
            vec![
                Op::Kick {
                    b: 1.0 / 6.0,
                    gamma: g
                },
                Op::Drift(0.5),
                Op::Kick {
                    b: 2.0 / 3.0,
                    gamma: 0.0
                },
                Op::Drift(0.5),
                Op::Kick {
                    b: 1.0 / 6.0,
                    gamma: g
                },
            ]
        );
        assert_eq!(Scheme::by_name("sbab2c").unwrap().kicks_per_step(), 2);
    }
}
