//! DOP853: the explicit Runge–Kutta pair of order 8(5,3) of Dormand & Prince with Hairer's
//! error estimate, step-size controller and order-7 dense output (Hairer, Nørsett & Wanner,
//! *Solving ODEs I*, 2nd ed., §II.5, §II.6, §II.10). Applied to the orbit and its deviation
//! vectors as one system: q' = p, p' = −∇V, δq' = δp, δp' = −D²V δq.
//!
//! The coefficients are the published ones; the code is this project's. The stiffness test
//! of Hairer's code is omitted: Hamiltonian systems like these are not stiff, and the test
//! would only cost evaluations.

// Coefficients keep the digits their sources publish; f64 rounds them once.
#![allow(clippy::excessive_precision)]

use crate::adaptive::stepping::{phase_lane, set_phase_lane, LaneSteps, StepFailure};
use crate::arith::real::{Lanes, Real};
use crate::phase::Phase;
use crate::systems::hamiltonian::Hamiltonian;

// 8th-order weights (stages 1, 6..12).
const B: [f64; 8] = [
    5.429_373_411_656_876_223_805_357_663_63e-2,
    4.450_312_892_752_408_881_441_139_505_66,
    1.891_517_899_314_500_383_042_815_990_44,
    -5.801_203_960_010_584_781_467_211_422_7,
    3.111_643_669_578_198_944_089_160_623_7e-1,
    -1.521_609_496_625_160_785_561_788_068_05e-1,
    2.013_654_008_040_303_483_747_765_375_01e-1,
    4.471_061_572_777_259_051_768_855_690_43e-2,
];
// 3rd-order error estimate weights on stages 1, 9, 12.
const BHH: [f64; 3] = [
    0.244_094_488_188_976_377_952_755_905_512,
    0.733_846_688_281_611_857_341_361_741_547,
    0.220_588_235_294_117_647_058_823_529_412e-1,
];
// 5th-order error estimate weights on stages 1, 6..12.
const ER: [f64; 8] = [
    0.131_200_449_941_948_807_325_010_299_6e-1,
    -0.122_515_644_637_620_444_072_056_975_3e1,
    -0.495_758_949_657_250_191_521_407_995_2,
    0.166_437_718_245_498_653_696_153_041_5e1,
    -0.350_328_848_749_973_681_688_648_729_0,
    0.334_179_118_713_017_479_029_731_884_1,
    0.819_232_064_851_157_124_657_074_261_3e-1,
    -0.223_553_078_638_862_952_588_442_784_5e-1,
];

// The coupling coefficients a_ij, row by row, with the stage indices they multiply.
const A2: [(usize, f64); 1] = [(0, 5.260_015_195_876_773_187_855_875_444_88e-2)];
const A3: [(usize, f64); 2] = [
    (0, 1.972_505_698_453_789_945_445_953_291_83e-2),
    (1, 5.917_517_095_361_369_836_337_859_875_49e-2),
];
const A4: [(usize, f64); 2] = [
    (0, 2.958_758_547_680_684_918_168_929_937_75e-2),
    (2, 8.876_275_643_042_054_754_506_789_813_24e-2),
];
const A5: [(usize, f64); 3] = [
    (0, 2.413_651_341_592_666_855_023_697_986_65e-1),
    (2, -8.845_494_793_282_860_853_448_649_627_17e-1),
    (3, 9.248_340_032_617_920_031_157_379_665_43e-1),
];
const A6: [(usize, f64); 3] = [
    (0, 3.703_703_703_703_703_703_703_703_703_7e-2),
    (3, 1.708_286_087_294_738_712_796_044_821_73e-1),
    (4, 1.254_676_875_668_224_250_166_918_141_23e-1),
];
const A7: [(usize, f64); 4] = [
    (0, 3.710_937_5e-2),
    (3, 1.702_522_110_195_440_393_149_780_602_72e-1),
    (4, 6.021_653_898_045_596_068_502_193_972_83e-2),
    (5, -1.757_812_5e-2),
];
const A8: [(usize, f64); 5] = [
    (0, 3.709_200_011_850_479_271_087_793_198_36e-2),
    (3, 1.703_839_257_122_399_938_102_140_547_05e-1),
    (4, 1.072_620_304_463_732_846_518_091_991_68e-1),
    (5, -1.531_943_774_862_440_175_279_361_582_36e-2),
    (6, 8.273_789_163_814_022_887_584_737_660_02e-3),
];
const A9: [(usize, f64); 6] = [
    (0, 6.241_109_587_160_757_171_144_295_778_12e-1),
    (3, -3.360_892_629_446_941_294_068_571_098_25),
    (4, -8.682_193_468_417_260_068_181_898_914_53e-1),
    (5, 2.759_209_969_944_670_830_494_156_007_97e1),
    (6, 2.015_406_755_047_789_340_861_867_889_79e1),
    (7, -4.348_988_418_106_995_884_773_662_551_44e1),
];
const A10: [(usize, f64); 7] = [
    (0, 4.776_625_364_382_643_658_904_339_085_27e-1),
    (3, -2.488_114_619_971_667_641_926_425_864_68),
    (4, -5.902_908_268_368_429_963_714_464_757_43e-1),
    (5, 2.123_005_144_818_119_423_472_889_498_97e1),
    (6, 1.527_923_363_288_242_358_325_969_229_38e1),
    (7, -3.328_821_096_898_486_291_944_532_655_87e1),
    (8, -2.033_120_170_850_862_613_582_229_285_93e-2),
];
const A11: [(usize, f64); 8] = [
    (0, -9.371_424_300_859_873_257_170_402_165_8e-1),
    (3, 5.186_372_428_844_063_708_300_238_532_09),
    (4, 1.091_437_348_996_729_578_185_002_546_54),
    (5, -8.149_787_010_746_926_125_139_972_673_57),
    (6, -1.852_006_565_999_695_986_415_661_807_01e1),
    (7, 2.273_948_709_935_050_428_189_700_567_34e1),
    (8, 2.493_605_552_679_652_389_870_893_967_62),
    (9, -3.046_764_471_898_219_500_382_366_902_2),
];
const A12: [(usize, f64); 9] = [
    (0, 2.273_310_147_516_538_207_923_597_684_49),
    (3, -1.053_449_546_673_725_019_840_666_898_79e1),
    (4, -2.000_872_058_224_862_499_096_757_184_44),
    (5, -1.795_893_186_311_879_891_727_659_505_34e1),
    (6, 2.794_888_452_941_996_005_084_998_088_37e1),
    (7, -2.858_998_277_135_023_694_740_655_086_74),
    (8, -8.872_856_933_530_629_544_335_492_892_58),
    (9, 1.236_056_717_579_430_306_472_662_015_28e1),
    (10, 6.433_927_460_157_635_303_559_704_840_46e-1),
];
// The three extra stages of the dense output; index 12 is the FSAL slope f(t + h, y1).
const A14: [(usize, f64); 8] = [
    (0, 5.616_750_228_304_795_233_929_092_196_81e-2),
    (6, 2.535_002_102_166_248_110_887_947_653_33e-1),
    (7, -2.462_390_374_708_024_899_174_414_754_41e-1),
    (8, -1.241_914_232_638_163_604_690_101_406_26e-1),
    (9, 1.532_917_982_787_656_973_120_632_268_5e-1),
    (10, 8.201_052_295_634_689_884_916_666_020_57e-3),
    (11, 7.567_897_660_545_699_761_386_035_895_84e-3),
    (12, -8.298e-3),
];
const A15: [(usize, f64); 8] = [
    (0, 3.183_464_816_350_214_050_607_684_732_61e-2),
    (5, 2.830_090_967_236_677_552_883_229_614_02e-2),
    (6, 5.354_198_830_743_856_762_237_973_843_72e-2),
    (7, -5.492_374_857_139_098_846_465_693_403_06e-2),
    (10, -1.083_473_286_972_493_228_585_093_169_94e-4),
    (11, 3.825_710_908_356_584_129_549_201_923_23e-4),
    (12, -3.404_650_086_874_045_608_029_771_144_92e-4),
    (13, 1.413_124_436_746_325_002_780_746_183_66e-1),
];
const A16: [(usize, f64); 8] = [
    (0, -4.288_963_015_837_919_234_085_735_386_92e-1),
    (5, -4.697_621_415_361_163_843_144_494_472_06),
    (6, 7.683_421_196_062_599_041_842_409_538_78),
    (7, 4.068_989_818_397_110_079_702_135_543_31),
    (8, 3.567_271_874_552_811_092_706_695_430_21e-1),
    (12, -1.399_024_165_159_014_621_294_180_097_34e-3),
    (13, 2.947_514_789_152_772_338_955_627_214_9),
    (14, -9.150_958_472_179_870_010_818_701_871_38),
];
// Dense-output coefficients d_i,j for i = 4..7 on stages 1, 6..12 and then 13 (FSAL), 14..16.
const D: [[f64; 12]; 4] = [
    [
        -0.842_893_827_610_901_286_513_534_911_42e1,
        0.566_714_953_519_377_769_625_317_835_90,
        -0.306_894_994_594_989_169_127_973_047_27e1,
        0.238_466_765_651_206_982_877_281_496_80e1,
        0.211_703_458_244_502_827_671_551_499_46e1,
        -0.871_391_583_777_972_992_067_899_074_90,
        0.224_043_743_026_078_827_585_417_716_50e1,
        0.631_578_778_769_468_818_155_702_492_90,
        -0.889_903_364_513_333_108_206_981_174_00e-1,
        0.181_485_055_208_547_272_566_564_049_62e2,
        -0.919_463_239_247_835_540_004_519_844_36e1,
        -0.443_603_638_759_489_396_643_105_720_00e1,
    ],
    [
        0.104_275_086_425_791_346_034_131_510_09e2,
        0.242_283_491_775_258_182_884_301_753_19e3,
        0.165_200_451_717_270_281_985_053_948_87e3,
        -0.374_546_754_722_690_202_795_183_121_52e3,
        -0.221_136_668_531_253_060_362_709_385_78e2,
        0.773_343_266_847_226_383_896_038_988_08e1,
        -0.306_740_847_310_893_981_820_612_136_26e2,
        -0.933_213_052_643_022_787_295_672_217_06e1,
        0.156_972_381_217_708_438_861_310_910_75e2,
        -0.311_394_032_195_651_776_772_828_504_11e2,
        -0.935_292_435_884_447_838_657_138_626_64e1,
        0.358_168_414_863_940_837_524_658_985_40e2,
    ],
    [
        0.199_850_532_420_024_338_209_876_536_17e2,
        -0.387_037_308_749_351_765_551_059_017_42e3,
        -0.189_178_138_195_167_568_828_308_383_28e3,
        0.527_808_159_205_423_649_005_610_166_86e3,
        -0.115_739_025_399_596_301_261_418_711_34e2,
        0.688_123_269_469_630_001_696_669_226_61e1,
        -0.100_060_509_669_108_384_031_838_609_80e1,
        0.777_713_779_805_344_320_928_692_657_40,
        -0.277_820_575_235_350_840_659_320_043_39e1,
        -0.601_966_952_312_641_207_582_673_808_46e2,
        0.843_204_055_066_771_610_181_599_037_84e2,
        0.119_922_911_361_827_893_280_351_300_30e2,
    ],
    [
        -0.256_939_334_627_037_490_033_125_861_29e2,
        -0.154_189_748_690_236_433_740_539_936_27e3,
        -0.231_529_379_176_045_495_675_360_391_09e3,
        0.357_639_117_910_614_123_782_853_499_10e3,
        0.934_053_241_836_243_100_039_076_917_04e2,
        -0.374_583_231_364_516_331_568_751_393_51e2,
        0.104_099_649_508_962_300_451_472_461_84e3,
        0.298_402_934_266_605_031_233_443_635_79e2,
        -0.435_334_565_900_111_437_544_321_750_58e2,
        0.963_245_539_591_882_829_483_949_506_00e2,
        -0.391_772_616_756_154_391_652_314_861_72e2,
        -0.149_726_836_257_985_625_814_221_252_76e3,
    ],
];

/// A Runge–Kutta pair with two embedded error estimates and dense output, as data: what
/// [`Dop853`] and [`Dop853Lanes`] step with.
#[derive(Clone, Copy, Debug)]
pub struct Tableau {
    /// Nodes c_1 … c_16 (the thirteenth stage is the next step's first, FSAL). The systems here
    /// are autonomous, so only checks of the tableau read them.
    pub nodes: [f64; 16],
    /// The coupling coefficients a_ij of stages 2 … 12, each with the stage index it multiplies.
    pub rows: [&'static [(usize, f64)]; 11],
    /// The rows of the dense output's extra stages 14 … 16.
    pub dense_rows: [&'static [(usize, f64)]; 3],
    /// The stages whose slopes the solution and the 5th-order estimate weigh.
    pub main: [usize; 8],
    /// The 8th-order weights b_i on [`Self::main`].
    pub weights: [f64; 8],
    /// The 5th-order error estimate's weights on [`Self::main`].
    pub error5: [f64; 8],
    /// The 3rd-order estimate's weights, each with its stage index (subtracted from the 8th-order
    /// increment).
    pub error3: [(usize, f64); 3],
    /// The dense output's coefficients d_ij, i = 4 … 7, on [`Self::dense_stages`].
    pub dense: [[f64; 12]; 4],
    /// The stages the dense output weighs: [`Self::main`], then 13 (FSAL) and 14 … 16.
    pub dense_stages: [usize; 12],
}

/// Dormand & Prince's 8(5,3) pair with Hairer's estimates and order-7 dense output.
pub const DOP853_TABLEAU: Tableau = Tableau {
    nodes: [
        0.0,
        0.526_001_519_587_677_318_785_587_544_488e-1,
        0.789_002_279_381_515_978_178_381_316_732e-1,
        0.118_350_341_907_227_396_726_757_197_510,
        0.281_649_658_092_772_603_273_242_802_490,
        0.333_333_333_333_333_333_333_333_333_333,
        0.25,
        0.307_692_307_692_307_692_307_692_307_692,
        0.651_282_051_282_051_282_051_282_051_282,
        0.6,
        0.857_142_857_142_857_142_857_142_857_142,
        1.0,
        1.0,
        0.1,
        0.2,
        0.777_777_777_777_777_777_777_777_777_778,
    ],
    rows: [&A2, &A3, &A4, &A5, &A6, &A7, &A8, &A9, &A10, &A11, &A12],
    dense_rows: [&A14, &A15, &A16],
    main: [0, 5, 6, 7, 8, 9, 10, 11],
    weights: B,
    error5: ER,
    error3: [(0, BHH[0]), (8, BHH[1]), (11, BHH[2])],
    dense: D,
    dense_stages: [0, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15],
};

/// The right-hand side of the orbit and its variational equations.
#[inline(always)]
pub fn rhs<H: Hamiltonian<N>, T: Real, const N: usize, const K: usize>(
    ham: &H,
    y: &Phase<T, N, K>,
) -> Phase<T, N, K> {
    let g = ham.grad(&y.q);
    let h = ham.hessian(&y.q);
    let mut f = Phase {
        q: y.p,
        p: [T::splat(0.0); N],
        dq: y.dp,
        dp: [[T::splat(0.0); N]; K],
    };
    for i in 0..N {
        f.p[i] = -g[i];
    }
    for k in 0..K {
        for i in 0..N {
            let mut s = T::splat(0.0);
            for j in 0..N {
                s = h[i][j].mul_add(y.dq[k][j], s);
            }
            f.dp[k][i] = -s;
        }
    }
    f
}

/// y + h Σ_j a_j k_j over one row of the tableau.
#[inline(always)]
fn stage<T: Real, const N: usize, const K: usize>(
    y: &Phase<T, N, K>,
    h: T,
    row: &[(usize, f64)],
    k: &[Phase<T, N, K>],
) -> Phase<T, N, K> {
    let mut acc = Phase::zero();
    for &(j, a) in row {
        acc.axpy(T::splat(a), &k[j]);
    }
    let mut out = *y;
    out.axpy(h, &acc);
    out
}

/// One attempt of size `h` from y with slope f0: fills the stages `k[0..12]` and returns the
/// 8th-order solution and the 5th- and 3rd-order error estimates. Generic so that SIMD lanes
/// ([`Dop853Lanes`]) compute in each lane exactly what [`Dop853::step`] computes.
#[inline(always)]
fn attempt<H: Hamiltonian<N>, T: Real, const N: usize, const K: usize>(
    ham: &H,
    y: &Phase<T, N, K>,
    f0: &Phase<T, N, K>,
    h: T,
    k: &mut [Phase<T, N, K>; 16],
) -> (Phase<T, N, K>, Phase<T, N, K>, Phase<T, N, K>) {
    let tab = &DOP853_TABLEAU;
    k[0] = *f0;
    for (s, row) in tab.rows.iter().enumerate() {
        let ys = stage(y, h, row, &k[..]);
        k[s + 1] = rhs(ham, &ys);
    }
    let mut incr = Phase::zero();
    for (w, &j) in tab.weights.iter().zip(&tab.main) {
        incr.axpy(T::splat(*w), &k[j]);
    }
    let mut y1 = *y;
    y1.axpy(h, &incr);
    let mut e5 = Phase::zero();
    for (w, &j) in tab.error5.iter().zip(&tab.main) {
        e5.axpy(T::splat(*w), &k[j]);
    }
    let mut e3 = incr;
    for &(j, w) in &tab.error3 {
        e3.axpy(T::splat(-w), &k[j]);
    }
    (y1, e5, e3)
}

/// Tolerances and controller parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dop853Config {
    /// Relative tolerance.
    pub rtol: f64,
    /// Absolute tolerance.
    pub atol: f64,
    /// Safety factor of the step prediction (0.9).
    pub safe: f64,
    /// Bounds of h_new/h (0.333 and 6).
    pub fac_min: f64,
    /// Upper bound of h_new/h (6).
    pub fac_max: f64,
    /// Largest step allowed.
    pub h_max: f64,
}

impl Dop853Config {
    /// Hairer's defaults with rtol = atol = δ.
    pub fn with_delta(delta: f64) -> Self {
        Dop853Config {
            rtol: delta,
            atol: delta,
            safe: 0.9,
            fac_min: 0.333,
            fac_max: 6.0,
            h_max: f64::INFINITY,
        }
    }
}

/// The coefficients of the order-7 dense output of one accepted step: y(t_old + θh) =
/// c0 + θ(c1 + θ'(c2 + θ(c3 + θ'(c4 + θ(c5 + θ'(c6 + θ c7)))))), θ' = 1 − θ.
#[derive(Clone, Copy, Debug)]
pub struct Dense<const N: usize, const K: usize> {
    /// Start of the step.
    pub t_old: f64,
    /// Size of the step.
    pub h: f64,
    c: [Phase<f64, N, K>; 8],
}

impl<const N: usize, const K: usize> Dense<N, K> {
    /// An interpolant of no step yet.
    pub fn empty() -> Self {
        Dense {
            t_old: 0.0,
            h: 0.0,
            c: [Phase::zero(); 8],
        }
    }

    /// The interpolated state at t in [t_old, t_old + h].
    pub fn at(&self, t: f64) -> Phase<f64, N, K> {
        let th = (t - self.t_old) / self.h;
        let th1 = 1.0 - th;
        let mut out = self.c[7];
        for (i, c) in self.c[..7].iter().enumerate().rev() {
            // Alternate factors θ and θ' from the inside out.
            let f = if i % 2 == 0 { th } else { th1 };
            out.scale(f);
            out.axpy(1.0, c);
        }
        out
    }
}

/// The start and size of the last accepted step.
#[derive(Clone, Copy, Debug)]
struct LastStep<const N: usize, const K: usize> {
    t: f64,
    h: f64,
    y0: Phase<f64, N, K>,
    y1: Phase<f64, N, K>,
}

/// A DOP853 integration in progress: state, FSAL slope and the controller's memory.
#[derive(Clone, Debug)]
pub struct Dop853<'h, H, const N: usize, const K: usize> {
    ham: &'h H,
    /// Tolerances and controller parameters.
    pub config: Dop853Config,
    /// Current time.
    pub t: f64,
    /// Current state.
    pub y: Phase<f64, N, K>,
    /// f(t, y), reused as the first stage of the next step (FSAL).
    f0: Phase<f64, N, K>,
    /// The stages of the last attempt; after an accepted step, what its dense output needs
    /// (index 12 holds the FSAL slope at its end), with the step's start in `last`.
    k: [Phase<f64, N, K>; 16],
    last: LastStep<N, K>,
    /// The step-size controller.
    pub ctl: Control,
    /// Right-hand-side evaluations so far.
    pub evaluations: u64,
}

/// Hairer's step-size controller: its memory, and the size of the next attempt.
#[derive(Clone, Copy, Debug)]
pub struct Control {
    /// The step to try next.
    pub h: f64,
    fac_old: f64,
    rejected_last: bool,
    /// Accepted steps so far.
    pub accepted: u64,
    /// Rejected attempts so far.
    pub rejected: u64,
}

impl Control {
    fn new() -> Self {
        Control {
            h: 0.0,
            fac_old: 1e-4,
            rejected_last: false,
            accepted: 0,
            rejected: 0,
        }
    }

    /// The next attempt from t toward t_end: its size, the size the controller asked for, and
    /// whether it lands on t_end.
    #[inline(always)]
    fn plan(&self, c: &Dop853Config, t: f64, t_end: f64) -> Result<(f64, f64, bool), StepFailure> {
        let h_try = self.h.min(c.h_max);
        let mut h = h_try;
        let mut last = false;
        if t + 1.01 * h >= t_end {
            h = t_end - t;
            last = true;
        }
        if 0.1 * h.abs() <= t.abs() * f64::EPSILON || h <= 0.0 {
            return Err(StepFailure::StepTooSmall { t });
        }
        Ok((h, h_try, last))
    }

    /// Judges an attempt planned by [`Self::plan`] whose error is `err` (finite): true when it
    /// is accepted. Either way the next attempt's size is set.
    #[inline(always)]
    fn judge(&mut self, c: &Dop853Config, err: f64, (h, h_try, last): (f64, f64, bool)) -> bool {
        let fac11 = || err.powf(1.0 / 8.0);
        let rejected_last = self.rejected_last;
        let predict = || {
            let fac = (fac11() / c.safe).clamp(1.0 / c.fac_max, 1.0 / c.fac_min);
            let h_new = h / fac;
            if rejected_last {
                h_new.min(h)
            } else {
                h_new
            }
        };
        if err <= 1.0 {
            self.fac_old = err.max(1e-4);
            self.rejected_last = false;
            self.accepted += 1;
            // A step cut short to land on t_end says little about the natural step: keep
            // the prediction made before the cut (the restart protocol feeds it back).
            // A prediction is at most h·fac_max, so when that stays below h_try the
            // prediction (a root of err) is not needed: the restart protocol at small τ.
            self.h = if last && h < h_try {
                if h * c.fac_max * (1.0 + 4.0 * f64::EPSILON) < h_try {
                    h_try
                } else {
                    predict().max(h_try)
                }
            } else {
                predict()
            };
            return true;
        }
        self.h = h / (1.0 / c.fac_min).min(fac11() / c.safe);
        self.rejected_last = true;
        if self.accepted >= 1 {
            self.rejected += 1;
        }
        false
    }
}

/// The dense output of the accepted step `last` whose stages 0..=12 are in `k` (3 more
/// evaluations fill 13..=15).
fn dense_from<H: Hamiltonian<N>, const N: usize, const K: usize>(
    ham: &H,
    last: &LastStep<N, K>,
    k: &mut [Phase<f64, N, K>; 16],
    d: &mut Dense<N, K>,
) {
    let LastStep { t, h, y0, y1 } = *last;
    let tab = &DOP853_TABLEAU;
    for (i, row) in tab.dense_rows.iter().enumerate() {
        let ys = stage(&y0, h, row, &k[..]);
        k[13 + i] = rhs(ham, &ys);
    }
    let mut c1 = y1;
    c1.axpy(-1.0, &y0);
    let mut c2 = k[0];
    c2.scale(h);
    c2.axpy(-1.0, &c1);
    let mut c3 = c1;
    c3.axpy(-h, &k[12]);
    c3.axpy(-1.0, &c2);
    let mut cs = [Phase::zero(); 4];
    for (row, out) in tab.dense.iter().zip(cs.iter_mut()) {
        for (w, &j) in row.iter().zip(&tab.dense_stages) {
            out.axpy(*w, &k[j]);
        }
        out.scale(h);
    }
    d.t_old = t;
    d.h = h;
    d.c = [y0, c1, c2, c3, cs[0], cs[1], cs[2], cs[3]];
}

/// Hairer's combined error estimate of an attempt of size h from y0 to y1 with the estimates
/// e5 and e3: err = |h| E5 / sqrt(n (E5 + 0.01 E3)); accepted when ≤ 1.
#[inline(always)]
fn error_norm<const N: usize, const K: usize>(
    c: &Dop853Config,
    (y0, y1): (&Phase<f64, N, K>, &Phase<f64, N, K>),
    (e5, e3): (&Phase<f64, N, K>, &Phase<f64, N, K>),
    h: f64,
) -> f64 {
    let (mut err5, mut err3) = (0.0, 0.0);
    y0.zip3_for_each(y1, e5, e3, |y0, y1, a, b| {
        let sk = c.atol + c.rtol * y0.abs().max(y1.abs());
        err5 += (a / sk) * (a / sk);
        err3 += (b / sk) * (b / sk);
    });
    let mut deno = err5 + 0.01 * err3;
    if deno <= 0.0 {
        deno = 1.0;
    }
    let dim = (2 * N * (K + 1)) as f64;
    h.abs() * err5 * (1.0 / (dim * deno)).sqrt()
}

impl<'h, H: Hamiltonian<N>, const N: usize, const K: usize> Dop853<'h, H, N, K> {
    /// Starts at (t, y); the first step comes from Hairer's initial-step heuristic.
    pub fn new(ham: &'h H, config: Dop853Config, t: f64, y: Phase<f64, N, K>) -> Self {
        let f0 = rhs(ham, &y);
        let mut s = Dop853 {
            ham,
            config,
            t,
            y,
            f0,
            k: [Phase::zero(); 16],
            last: LastStep {
                t,
                h: 0.0,
                y0: y,
                y1: y,
            },
            ctl: Control::new(),
            evaluations: 1,
        };
        s.ctl.h = s.initial_step();
        s
    }

    /// Hairer's HINIT for order 8: an explicit Euler probe of the solution's scale.
    fn initial_step(&mut self) -> f64 {
        let c = self.config;
        let (mut dnf, mut dny) = (0.0, 0.0);
        self.y.zip_for_each(&self.f0, |y, f| {
            let sk = c.atol + c.rtol * y.abs();
            dnf += (f / sk) * (f / sk);
            dny += (y / sk) * (y / sk);
        });
        let mut h = if dnf <= 1e-10 || dny <= 1e-10 {
            1e-6
        } else {
            (dny / dnf).sqrt() * 0.01
        };
        h = h.min(c.h_max);
        let mut y1 = self.y;
        y1.axpy(h, &self.f0);
        let f1 = rhs(self.ham, &y1);
        self.evaluations += 1;
        let mut d2 = 0.0;
        let y0 = self.y;
        let mut diff = f1;
        diff.axpy(-1.0, &self.f0);
        diff.zip_for_each(&y0, |d, y| {
            let sk = c.atol + c.rtol * y.abs();
            d2 += (d / sk) * (d / sk);
        });
        let d2 = d2.sqrt() / h;
        let d12 = d2.max(dnf.sqrt());
        let h1 = if d12 <= 1e-15 {
            (h * 1e-3).max(1e-6)
        } else {
            (0.01 / d12).powf(1.0 / 8.0)
        };
        (100.0 * h).min(h1).min(c.h_max)
    }

    /// After the caller changed `y` (renormalisation), recompute the FSAL slope.
    pub fn state_changed(&mut self) {
        self.f0 = rhs(self.ham, &self.y);
        self.evaluations += 1;
    }

    /// Takes one accepted step that does not pass `t_end` (landing on it exactly when it is
    /// within reach), retrying rejected attempts. With `dense`, also fills the step's dense
    /// output (3 more evaluations).
    pub fn step(&mut self, t_end: f64, dense: Option<&mut Dense<N, K>>) -> Result<(), StepFailure> {
        let c = self.config;
        loop {
            let plan = self.ctl.plan(&c, self.t, t_end)?;
            let (h, _, last) = plan;
            let (y1, e5, e3) = attempt(self.ham, &self.y, &self.f0, h, &mut self.k);
            self.evaluations += 11;
            let err = error_norm(&c, (&self.y, &y1), (&e5, &e3), h);
            if !err.is_finite() {
                return Err(StepFailure::NonFinite { t: self.t });
            }
            if self.ctl.judge(&c, err, plan) {
                let f1 = rhs(self.ham, &y1);
                self.evaluations += 1;
                self.k[12] = f1;
                self.last = LastStep {
                    t: self.t,
                    h,
                    y0: self.y,
                    y1,
                };
                self.t = if last { t_end } else { self.t + h };
                self.y = y1;
                self.f0 = f1;
                if let Some(d) = dense {
                    self.dense_output(d);
                }
                return Ok(());
            }
        }
    }

    /// Fills `d` with the dense output of the last accepted step (3 more evaluations). Valid
    /// until the next call of [`Self::step`] (a renormalisation in between does not matter).
    pub fn dense_output(&mut self, d: &mut Dense<N, K>) {
        dense_from(self.ham, &self.last, &mut self.k, d);
        self.evaluations += 3;
    }

    /// One step of exactly `h`, with no error control: for measuring the method's order.
    pub fn fixed_step(&mut self, h: f64) {
        let mut k = [Phase::<f64, N, K>::zero(); 16];
        k[0] = self.f0;
        let tab = &DOP853_TABLEAU;
        for (s, row) in tab.rows.iter().enumerate() {
            let ys = stage(&self.y, h, row, &k);
            k[s + 1] = rhs(self.ham, &ys);
        }
        let mut incr = Phase::zero();
        for (w, &j) in tab.weights.iter().zip(&tab.main) {
            incr.axpy(*w, &k[j]);
        }
        self.y.axpy(h, &incr);
        self.t += h;
        self.f0 = rhs(self.ham, &self.y);
        self.evaluations += 12;
    }

    /// One step of exactly `h` with dense output, no error control (tests).
    pub fn fixed_step_dense(&mut self, h: f64) -> Dense<N, K> {
        let saved = (self.config, self.ctl.h);
        self.config.rtol = 1e300;
        self.config.atol = 1e300;
        self.ctl.h = h;
        let mut d = Dense::empty();
        let t_end = self.t + h;
        self.step(t_end, Some(&mut d)).expect("fixed step");
        (self.config, self.ctl.h) = saved;
        d
    }
}

/// `L` DOP853 integrations side by side, one per SIMD lane: the stages run on all lanes at
/// once, the error norm and the controller lane by lane with [`Dop853`]'s own functions, so
/// each lane computes exactly what [`Dop853`] computes for its orbit alone. A lane steps only
/// when asked; a lane whose attempt is rejected tries again in another pass over all lanes
/// while the lanes already accepted wait (their stages kept for the dense output).
pub struct Dop853Lanes<'h, H, const N: usize, const K: usize, const L: usize> {
    ham: &'h H,
    config: Dop853Config,
    t: [f64; L],
    t_prev: [f64; L],
    y: Phase<Lanes<L>, N, K>,
    f0: Phase<Lanes<L>, N, K>,
    k: Box<[Phase<Lanes<L>, N, K>; 16]>,
    /// The stages of lanes accepted in an earlier pass of the last step (`in_kept`).
    kept: Box<[Phase<Lanes<L>, N, K>; 16]>,
    in_kept: [bool; L],
    ctl: [Control; L],
    /// Each lane's last accepted step (which started at `t_prev`): its size, the state it
    /// started from and the one it reached (kept apart from `y`, which a renormalisation
    /// changes).
    last_h: [f64; L],
    last_y0: Phase<Lanes<L>, N, K>,
    last_y1: Phase<Lanes<L>, N, K>,
    /// The energy of each lane's state.
    energy: [f64; L],
    /// The driver's sums over each lane's state after its last step.
    sums: crate::adaptive::stepping::StepEnd<Lanes<L>, K>,
    /// Right-hand-side evaluations of each lane so far.
    pub evaluations: [u64; L],
}

/// dst ← src in the lanes where `mask` is set.
#[inline(always)]
fn blend<const N: usize, const K: usize, const L: usize>(
    dst: &mut Phase<Lanes<L>, N, K>,
    src: &Phase<Lanes<L>, N, K>,
    mask: &[bool; L],
) {
    if mask.iter().all(|&m| m) {
        *dst = *src;
        return;
    }
    // Selected by bit masks, without a branch per word (a test and a jump for each lane of
    // each word are a visible share of a batch step; figures: docs/performance.md).
    let keep: [u64; L] = core::array::from_fn(|l| if mask[l] { 0 } else { !0 });
    dst.zip_mut(src, |d, s| {
        for l in 0..L {
            let (d_bits, s_bits) = (d.0[l].to_bits(), s.0[l].to_bits());
            d.0[l] = f64::from_bits((d_bits & keep[l]) | (s_bits & !keep[l]));
        }
    });
}

/// [`error_norm`] of every lane at once, each lane's sums in the same order.
#[inline(always)]
fn error_norms<const N: usize, const K: usize, const L: usize>(
    c: &Dop853Config,
    (y0, y1): (&Phase<Lanes<L>, N, K>, &Phase<Lanes<L>, N, K>),
    (e5, e3): (&Phase<Lanes<L>, N, K>, &Phase<Lanes<L>, N, K>),
    h: &Lanes<L>,
) -> [f64; L] {
    let (mut err5, mut err3) = ([0.0; L], [0.0; L]);
    y0.zip3_for_each(y1, e5, e3, |y0, y1, a, b| {
        for l in 0..L {
            let sk = c.atol + c.rtol * y0.0[l].abs().max(y1.0[l].abs());
            err5[l] += (a.0[l] / sk) * (a.0[l] / sk);
            err3[l] += (b.0[l] / sk) * (b.0[l] / sk);
        }
    });
    let dim = (2 * N * (K + 1)) as f64;
    core::array::from_fn(|l| {
        let mut deno = err5[l] + 0.01 * err3[l];
        if deno <= 0.0 {
            deno = 1.0;
        }
        h.0[l].abs() * err5[l] * (1.0 / (dim * deno)).sqrt()
    })
}

impl<'h, H: Hamiltonian<N>, const N: usize, const K: usize, const L: usize>
    Dop853Lanes<'h, H, N, K, L>
{
    /// `L` idle lanes; [`Self::start`] starts each.
    pub fn new(ham: &'h H, config: Dop853Config) -> Self {
        Dop853Lanes {
            ham,
            config,
            t: [0.0; L],
            t_prev: [0.0; L],
            y: Phase::zero(),
            f0: Phase::zero(),
            k: Box::new([Phase::zero(); 16]),
            kept: Box::new([Phase::zero(); 16]),
            in_kept: [false; L],
            ctl: [Control::new(); L],
            last_h: [0.0; L],
            last_y0: Phase::zero(),
            last_y1: Phase::zero(),
            energy: [0.0; L],
            sums: crate::adaptive::stepping::StepEnd::of(&Phase::<_, N, K>::zero()),
            evaluations: [0; L],
        }
    }

    /// Starts lane `l` at (t0, y) as [`Dop853::new`] starts (the same first slope and step).
    pub fn start(&mut self, l: usize, t0: f64, y: &Phase<f64, N, K>) {
        let one = Dop853::new(self.ham, self.config, t0, *y);
        set_phase_lane(&mut self.y, l, y);
        set_phase_lane(&mut self.f0, l, &one.f0);
        self.t[l] = t0;
        self.t_prev[l] = t0;
        self.ctl[l] = one.ctl;
        self.energy[l] = self.ham.energy(&y.q, &y.p);
        self.evaluations[l] = one.evaluations;
    }

    /// The Hamiltonian integrated.
    pub fn hamiltonian(&self) -> &'h H {
        self.ham
    }

    /// Lane `l`'s current time.
    pub fn t(&self, l: usize) -> f64 {
        self.t[l]
    }

    /// Where lane `l`'s last accepted step started.
    pub fn t_prev(&self, l: usize) -> f64 {
        self.t_prev[l]
    }

    /// Lane `l`'s accepted steps.
    pub fn steps(&self, l: usize) -> u64 {
        self.ctl[l].accepted
    }

    /// Lane `l`'s current state.
    pub fn state(&self, l: usize) -> Phase<f64, N, K> {
        phase_lane(&self.y, l)
    }

    /// The energy of lane `l`'s state (renormalising leaves it alone).
    pub fn energy(&self, l: usize) -> f64 {
        self.energy[l]
    }

    /// The driver's sums over lane `l`'s state after its last step.
    pub fn step_end(&self, l: usize) -> crate::adaptive::stepping::StepEnd<f64, K> {
        self.sums.lane(l)
    }

    /// Every lane of `mask` renormalised as [`crate::adaptive::stepping::unit_vectors`] would, and
    /// its slope recomputed as [`Dop853::state_changed`] does, all lanes at once; each such lane's
    /// factor.
    #[inline(always)]
    pub fn renormalise(&mut self, mask: &[bool; L]) -> [f64; L] {
        if !mask.contains(&true) {
            return [1.0; L];
        }
        let factors =
            crate::adaptive::stepping::unit_deviations_lanes(&mut self.y.dq, &mut self.y.dp, mask);
        let f = rhs(self.ham, &self.y);
        blend(&mut self.f0, &f, mask);
        for l in (0..L).filter(|&l| mask[l]) {
            self.evaluations[l] += 1;
        }
        factors
    }

    /// [`Self::renormalise`] of the lanes of `renormalise`, then [`Self::step`].
    #[inline(always)]
    pub fn renormalise_and_step(
        &mut self,
        renormalise: &[bool; L],
        t_end: &[Option<f64>; L],
    ) -> LaneSteps<L> {
        let factors = self.renormalise(renormalise);
        (self.step(t_end), factors)
    }

    /// One accepted step of every lane `l` with `t_end[l]` set, as [`Dop853::step`] takes
    /// it; the outcome of each such lane (`None` for the others). Inlined, so that a caller
    /// compiled for a wider instruction set runs the stages in it.
    #[inline(always)]
    pub fn step(&mut self, t_end: &[Option<f64>; L]) -> [Option<Result<(), StepFailure>>; L] {
        let c = self.config;
        let mut out = [None; L];
        self.in_kept = [false; L];
        loop {
            let mut plans = [None; L];
            let mut h = Lanes([0.0; L]);
            for l in 0..L {
                let Some(end) = t_end[l].filter(|_| out[l].is_none()) else {
                    continue;
                };
                match self.ctl[l].plan(&c, self.t[l], end) {
                    Ok(plan) => {
                        h.0[l] = plan.0;
                        plans[l] = Some((end, plan));
                    }
                    Err(e) => out[l] = Some(Err(e)),
                }
            }
            if plans.iter().all(Option::is_none) {
                return out;
            }
            let (y1, e5, e3) = attempt(self.ham, &self.y, &self.f0, h, &mut self.k);
            let errs = error_norms(&c, (&self.y, &y1), (&e5, &e3), &h);
            let mut accepted = [false; L];
            for l in 0..L {
                let Some((_, plan)) = plans[l] else { continue };
                self.evaluations[l] += 11;
                if !errs[l].is_finite() {
                    out[l] = Some(Err(StepFailure::NonFinite { t: self.t[l] }));
                } else if self.ctl[l].judge(&c, errs[l], plan) {
                    accepted[l] = true;
                }
            }
            if !accepted.contains(&true) {
                continue;
            }
            let f1 = rhs(self.ham, &y1);
            let retry = (0..L).any(|l| plans[l].is_some() && !accepted[l] && out[l].is_none());
            blend(&mut self.k[12], &f1, &accepted);
            blend(&mut self.last_y0, &self.y, &accepted);
            blend(&mut self.last_y1, &y1, &accepted);
            blend(&mut self.y, &y1, &accepted);
            blend(&mut self.f0, &f1, &accepted);
            // For all lanes at once: the driver reads them after every step.
            let energy = self.ham.energy(&y1.q, &y1.p);
            self.sums = crate::adaptive::stepping::StepEnd::of(&self.y);
            for l in (0..L).filter(|&l| accepted[l]) {
                self.energy[l] = energy.0[l];
                let (end, (h, _, last)) = plans[l].expect("accepted lanes had a plan");
                self.evaluations[l] += 1;
                self.last_h[l] = h;
                self.t_prev[l] = self.t[l];
                self.t[l] = if last { end } else { self.t[l] + h };
                out[l] = Some(Ok(()));
            }
            if retry {
                // Another pass will overwrite the stages these lanes' dense output needs.
                for j in 0..13 {
                    blend(&mut self.kept[j], &self.k[j], &accepted);
                }
                for l in (0..L).filter(|&l| accepted[l]) {
                    self.in_kept[l] = true;
                }
            }
        }
    }

    /// The dense output of lane `l`'s last step, as [`Dop853::dense_output`] fills it; valid
    /// until the next [`Self::step`].
    pub fn dense_output(&mut self, l: usize, d: &mut Dense<N, K>) {
        let from = if self.in_kept[l] { &self.kept } else { &self.k };
        let mut k: [Phase<f64, N, K>; 16] = core::array::from_fn(|j| {
            if j <= 12 {
                phase_lane(&from[j], l)
            } else {
                Phase::zero()
            }
        });
        let last = LastStep {
            t: self.t_prev[l],
            h: self.last_h[l],
            y0: phase_lane(&self.last_y0, l),
            y1: phase_lane(&self.last_y1, l),
        };
        dense_from(self.ham, &last, &mut k, d);
        self.evaluations[l] += 3;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tableau_rows_sum_to_their_nodes_and_weights_to_one() {
        let tab = &DOP853_TABLEAU;
        let rows = tab.rows.iter().zip(&tab.nodes[1..12]);
        let dense_rows = tab.dense_rows.iter().zip(&tab.nodes[13..]);
        for (i, (row, c)) in rows.chain(dense_rows).enumerate() {
            let s: f64 = row.iter().map(|(_, a)| a).sum();
            assert!((s - c).abs() < 1e-13, "row {i}: Σa = {s}, c = {c}");
        }
        assert!((tab.weights.iter().sum::<f64>() - 1.0).abs() < 1e-14);
        // The 5th-order estimate's weights sum to zero (it estimates a difference).
        assert!(tab.error5.iter().sum::<f64>().abs() < 1e-14);
        // The 3rd-order estimate's weights sum to one, as the weights they are subtracted from.
        assert!((tab.error3.iter().map(|(_, w)| w).sum::<f64>() - 1.0).abs() < 1e-14);
        assert_eq!(tab.dense_stages[..8], tab.main);
    }
}
