//! The grid of cells on a surface of section (Hénon–Heiles' q1 = 0, p1 > 0 unless the grid
//! is made [`Grid::on_surface`]), its tiles and canonical order.

use crate::surface::Surface;
use salient_core::section::CellLattice;
use std::sync::Arc;

/// The order in which fast PSS walks the grid's compatible cells: a property of the grid alone,
/// never of its tiles (tiles are units of work, and cutting the grid differently must not
/// change a label). Cell (i, j) has i along q2 and j along p2.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ScanOrder {
    /// A raster scan with q2 outer: i = 0, 1, … and, inside each, j = 0, 1, … (the cells'
    /// index order).
    #[default]
    Q2Outer,
    /// A raster scan with p2 outer: j outer, i inner.
    P2Outer,
    /// [`ScanOrder::Q2Outer`] backwards.
    Q2OuterReversed,
    /// [`ScanOrder::P2Outer`] backwards.
    P2OuterReversed,
    /// A permutation of [`ScanOrder::Q2Outer`] drawn from this seed (Fisher–Yates over
    /// splitmix64: the same seed gives the same order on every machine).
    Shuffle(u64),
}

impl ScanOrder {
    /// The spec's names of the orders (a shuffle takes its seed from `grid.order_seed`).
    pub const NAMES: [&'static str; 5] = [
        "q2-outer",
        "p2-outer",
        "q2-outer-reversed",
        "p2-outer-reversed",
        "shuffle",
    ];

    /// The order the spec names, with the seed a shuffle draws from.
    pub fn from_name(name: &str, seed: u64) -> Option<ScanOrder> {
        Some(match name {
            "q2-outer" => ScanOrder::Q2Outer,
            "p2-outer" => ScanOrder::P2Outer,
            "q2-outer-reversed" => ScanOrder::Q2OuterReversed,
            "p2-outer-reversed" => ScanOrder::P2OuterReversed,
            "shuffle" => ScanOrder::Shuffle(seed),
            _ => return None,
        })
    }

    /// The spec's name of the order.
    pub fn name(self) -> &'static str {
        match self {
            ScanOrder::Q2Outer => Self::NAMES[0],
            ScanOrder::P2Outer => Self::NAMES[1],
            ScanOrder::Q2OuterReversed => Self::NAMES[2],
            ScanOrder::P2OuterReversed => Self::NAMES[3],
            ScanOrder::Shuffle(_) => Self::NAMES[4],
        }
    }

    /// The compatible cells of an `n_q2 × n_p2` grid (`compatible[cell]`) in this order.
    fn arrange(self, n_q2: usize, n_p2: usize, compatible: &[bool]) -> Vec<u32> {
        let index = |i: usize, j: usize| (i * n_p2 + j) as u32;
        let q2_outer = || (0..n_q2).flat_map(move |i| (0..n_p2).map(move |j| index(i, j)));
        let p2_outer = || (0..n_p2).flat_map(move |j| (0..n_q2).map(move |i| index(i, j)));
        let keep = |c: &u32| compatible[*c as usize];
        match self {
            ScanOrder::Q2Outer => q2_outer().filter(keep).collect(),
            ScanOrder::P2Outer => p2_outer().filter(keep).collect(),
            ScanOrder::Q2OuterReversed => q2_outer().filter(keep).rev().collect(),
            ScanOrder::P2OuterReversed => p2_outer().filter(keep).rev().collect(),
            ScanOrder::Shuffle(seed) => {
                let mut cells: Vec<u32> = q2_outer().filter(keep).collect();
                let mut state = seed;
                for k in (1..cells.len()).rev() {
                    let r = splitmix64(&mut state);
                    // The multiply-shift maps r to 0..=k without a division; its bias is below
                    // 2^-32 for any grid Salient accepts.
                    let pick = ((r as u128 * (k as u128 + 1)) >> 64) as usize;
                    cells.swap(k, pick);
                }
                cells
            }
        }
    }
}

/// The next number of the splitmix64 sequence from `state`.
fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A rectangular grid over the section's two axes with its compatible cells in canonical
/// order. The fields and methods say q2 and p2 for the first and second axis: Hénon–Heiles'
/// axes, and whatever the [`Surface`] names for another system.
#[derive(Clone, Debug, PartialEq)]
pub struct Grid {
    /// The system and its section.
    pub surface: Arc<Surface>,
    /// The energy H of the section.
    pub energy: f64,
    /// Cells along q2.
    pub n_q2: usize,
    /// Cells along p2.
    pub n_p2: usize,
    /// Bounds (low, high) of q2.
    pub q2: (f64, f64),
    /// Bounds (low, high) of p2.
    pub p2: (f64, f64),
    /// A unit of work of `tile.0 × tile.1` cells ([`Grid::tile_count`]): the spec's tile, or
    /// the distributed scheduler's lease unit ([`Grid::retiled`]).
    pub tile: (usize, usize),
    /// The canonical order fast PSS walks the cells in.
    pub order: ScanOrder,
    compatible: Vec<bool>,
    /// [`Grid::spacing`], computed once: the cell of every crossing divides by it.
    step: (f64, f64),
    /// Compatible cells in canonical order ([`Grid::order`]).
    canonical: Vec<u32>,
    /// Canonical position of each compatible cell (u32::MAX for the others).
    position: Vec<u32>,
}

impl Grid {
    /// A grid of `n_q2 × n_p2` cells over the given bounds, split into tiles of `tile` cells,
    /// in the default canonical order. A cell is compatible when its centre lies on the section
    /// (p1² > 0).
    pub fn new(
        energy: f64,
        n_q2: usize,
        n_p2: usize,
        q2: (f64, f64),
        p2: (f64, f64),
        tile: (usize, usize),
    ) -> Self {
        Self::with_order(energy, n_q2, n_p2, q2, p2, tile, ScanOrder::default())
    }

    /// [`Grid::new`] walked in `order`.
    pub fn with_order(
        energy: f64,
        n_q2: usize,
        n_p2: usize,
        q2: (f64, f64),
        p2: (f64, f64),
        tile: (usize, usize),
        order: ScanOrder,
    ) -> Self {
        let surface = Surface::henon_heiles();
        Self::on_surface(surface, energy, [n_q2, n_p2], [q2, p2], tile, order)
    }

    /// A grid on `surface` of `cells[0] × cells[1]` cells along its axes within `bounds`. A
    /// cell is compatible when its centre lies on the section (the plane's momentum squared
    /// > 0 there).
    pub fn on_surface(
        surface: Arc<Surface>,
        energy: f64,
        [n_q2, n_p2]: [usize; 2],
        [q2, p2]: [(f64, f64); 2],
        tile: (usize, usize),
        order: ScanOrder,
    ) -> Self {
        assert!(n_q2 > 0 && n_p2 > 0 && tile.0 > 0 && tile.1 > 0);
        assert!(n_q2 * n_p2 <= u32::MAX as usize / 2);
        let mut g = Grid {
            surface,
            energy,
            n_q2,
            n_p2,
            q2,
            p2,
            tile,
            order,
            step: ((q2.1 - q2.0) / n_q2 as f64, (p2.1 - p2.0) / n_p2 as f64),
            compatible: vec![false; n_q2 * n_p2],
            canonical: Vec::new(),
            position: vec![u32::MAX; n_q2 * n_p2],
        };
        for cell in 0..n_q2 * n_p2 {
            let (x, y) = g.centre(cell as u32);
            g.compatible[cell] = g.surface.momentum_squared(energy, x, y) > 0.0;
        }
        g.canonical = order.arrange(n_q2, n_p2, &g.compatible);
        for (pos, &cell) in g.canonical.iter().enumerate() {
            g.position[cell as usize] = pos as u32;
        }
        g
    }

    /// Number of cells, compatible or not.
    pub fn cells(&self) -> usize {
        self.n_q2 * self.n_p2
    }

    /// Cell index of (i, j): i along q2, j along p2.
    pub fn index(&self, i: usize, j: usize) -> u32 {
        (i * self.n_p2 + j) as u32
    }

    /// (i, j) of a cell index.
    pub fn ij(&self, cell: u32) -> (usize, usize) {
        (cell as usize / self.n_p2, cell as usize % self.n_p2)
    }

    /// The cells' widths along q2 and p2.
    pub fn spacing(&self) -> (f64, f64) {
        self.step
    }

    /// The phase-space point cell `cell` starts from, in the coordinates the integrators run
    /// in ([`Surface::start`]); `None` for an incompatible cell.
    pub fn start<const N: usize>(&self, cell: u32) -> Option<([f64; N], [f64; N])> {
        let (x, y) = self.centre(cell);
        self.surface.start(self.energy, x, y)
    }

    /// The cell's centre (q2, p2): its initial condition.
    pub fn centre(&self, cell: u32) -> (f64, f64) {
        let (i, j) = self.ij(cell);
        let (dq, dp) = self.spacing();
        (
            self.q2.0 + (i as f64 + 0.5) * dq,
            self.p2.0 + (j as f64 + 0.5) * dp,
        )
    }

    /// The cell containing (q2, p2), if inside the grid.
    pub fn cell_of(&self, q2: f64, p2: f64) -> Option<u32> {
        let [cell] = self.cells_of(&[q2], &[p2]);
        cell
    }

    /// [`Grid::cell_of`] of `L` points at once, written over arrays so that the divisions go
    /// as vectors.
    pub fn cells_of<const L: usize>(&self, q2: &[f64; L], p2: &[f64; L]) -> [Option<u32>; L] {
        let (dq, dp) = self.step;
        let fi: [f64; L] = core::array::from_fn(|k| ((q2[k] - self.q2.0) / dq).floor());
        let fj: [f64; L] = core::array::from_fn(|k| ((p2[k] - self.p2.0) / dp).floor());
        core::array::from_fn(|k| {
            let (fi, fj) = (fi[k], fj[k]);
            (fi >= 0.0 && fj >= 0.0 && (fi as usize) < self.n_q2 && (fj as usize) < self.n_p2)
                .then(|| self.index(fi as usize, fj as usize))
        })
    }

    /// Whether every point within `r` of (q2, p2) in each coordinate gets the cell (or the
    /// absence of one) that [`Grid::cell_of`] gives (q2, p2).
    pub fn same_cell_within(&self, q2: f64, p2: f64, r: f64) -> bool {
        self.lattice().same_cell_within(q2, p2, r)
    }

    /// The grid's cells as a lattice of the section plane, the way [`Grid::cell_of`] divides
    /// it.
    pub fn lattice(&self) -> CellLattice {
        CellLattice {
            q2_origin: self.q2.0,
            p2_origin: self.p2.0,
            q2_width: self.step.0,
            p2_width: self.step.1,
        }
    }

    /// Whether `cell`'s centre lies on the section (p1² > 0).
    pub fn is_compatible(&self, cell: u32) -> bool {
        self.compatible[cell as usize]
    }

    /// Number of compatible cells.
    pub fn compatible_count(&self) -> usize {
        self.canonical.len()
    }

    /// Compatible cells in canonical order.
    pub fn canonical(&self) -> &[u32] {
        &self.canonical
    }

    /// Canonical position of every cell, `u32::MAX` for the incompatible ones.
    pub(crate) fn positions(&self) -> &[u32] {
        &self.position
    }

    /// Canonical position of a compatible cell.
    pub fn position(&self, cell: u32) -> Option<usize> {
        let p = self.position[cell as usize];
        (p != u32::MAX).then_some(p as usize)
    }

    /// Cells in a tile: `tile.0 × tile.1`.
    pub fn tile_size(&self) -> usize {
        self.tile.0 * self.tile.1
    }

    /// The same grid and canonical order cut into tiles of `cells` cells. Tiles cut the order,
    /// not the plane, so nothing but the units of work changes.
    pub fn retiled(mut self, cells: usize) -> Grid {
        self.tile = (1, cells.max(1));
        self
    }

    /// Number of tiles. A tile is a unit of work: [`Grid::tile_size`] consecutive compatible
    /// cells of the canonical order (the last one may hold fewer), numbered along the order.
    /// Cutting the order, not the plane, keeps a lease's cells next to each other in the
    /// order fast PSS commits in, whatever the order.
    pub fn tile_count(&self) -> usize {
        self.canonical.len().div_ceil(self.tile_size())
    }

    /// The index of the tile holding a compatible cell.
    pub fn tile_of(&self, cell: u32) -> Option<usize> {
        self.position(cell).map(|p| p / self.tile_size())
    }

    /// The cells of tile `index`, in canonical order.
    pub fn tile_cells(&self, index: usize) -> &[u32] {
        let size = self.tile_size();
        let start = (index * size).min(self.canonical.len());
        &self.canonical[start..(start + size).min(self.canonical.len())]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper_grid() -> Grid {
        let q2 = (
            0.5 + (160f64).to_radians().cos(),
            0.5 + (80f64).to_radians().cos(),
        );
        Grid::new(0.125, 400, 400, q2, (-0.5, 0.5), (20, 20))
    }

    /// Whenever `same_cell_within` says yes, every point of the square, corners, edges and
    /// inside, gets the centre's cell (or none, beyond the grid); it says no when the square
    /// straddles a cell's edge, down to a radius of one ulp of the coordinate.
    #[test]
    fn same_cell_within_agrees_with_cell_of() {
        let g = paper_grid();
        let (dq, dp) = g.spacing();
        let (mut yes, mut no) = (0, 0);
        for k in 0..20_000u64 {
            // A cheap spread of points, some beyond the grid, and radii from 1e-16 to 1e-3.
            let u = |m: u64| ((k * m) % 10_007) as f64 / 10_007.0;
            let (q2, p2) = (-0.5 + 1.25 * u(7_919), -0.55 + 1.1 * u(104_729));
            let r = 10f64.powf(-16.0 + 13.0 * u(1_299_709));
            let want = g.cell_of(q2, p2);
            if g.same_cell_within(q2, p2, r) {
                yes += 1;
                for a in [-1.0, -0.5, 0.0, 0.5, 1.0] {
                    for b in [-1.0, -0.3, 0.0, 0.7, 1.0] {
                        assert_eq!(g.cell_of(q2 + a * r, p2 + b * r), want, "{q2} {p2} {r}");
                    }
                }
            } else {
                no += 1;
            }
        }
        assert!(yes > 10_000 && no > 500, "{yes} {no}");
        // A point one ulp below an edge, with a radius of two ulps, straddles it.
        let edge = g.q2.0 + 17.0 * dq;
        let below = f64::from_bits(edge.to_bits() - 1);
        if g.cell_of(below, 0.001) != g.cell_of(edge, 0.001) {
            assert!(!g.same_cell_within(below, 0.001, 2.0 * (edge - below)));
        }
        assert!(!g.same_cell_within(g.q2.0 + 3.5 * dq, g.p2.0 + 9.0 * dp, 1e-9));
        assert!(g.same_cell_within(g.q2.0 + 3.5 * dq, g.p2.0 + 9.5 * dp, 1e-9));
    }

    #[test]
    fn cells_of_in_lanes_equals_the_scalar_formula() {
        let g = paper_grid();
        let (dq, dp) = g.spacing();
        let scalar = |q2: f64, p2: f64| {
            let (fi, fj) = (((q2 - g.q2.0) / dq).floor(), ((p2 - g.p2.0) / dp).floor());
            let inside = fi >= 0.0 && fj >= 0.0 && fi < g.n_q2 as f64 && fj < g.n_p2 as f64;
            inside.then(|| (fi as usize * g.n_p2 + fj as usize) as u32)
        };
        // Points spread over and beyond the grid, and points one ulp either side of edges
        // (where a different rounding would show).
        let edge = |x: f64, ulps: i64| f64::from_bits((x.to_bits() as i64 + ulps) as u64);
        let mut points = Vec::new();
        for k in 0..4_000u64 {
            let u = |m: u64| ((k * m) % 10_007) as f64 / 10_007.0;
            points.push((-0.5 + 1.25 * u(7_919), -0.55 + 1.1 * u(104_729)));
            let (i, j) = ((k % 401) as f64, ((k * 37) % 401) as f64);
            let (q2, p2) = (g.q2.0 + i * dq, g.p2.0 + j * dp);
            points.push((edge(q2, k as i64 % 3 - 1), edge(p2, (k / 3) as i64 % 3 - 1)));
        }
        let (mut inside, mut outside) = (0, 0);
        for group in points.chunks_exact(8) {
            let q2: [f64; 8] = core::array::from_fn(|k| group[k].0);
            let p2: [f64; 8] = core::array::from_fn(|k| group[k].1);
            for (k, cell) in g.cells_of(&q2, &p2).into_iter().enumerate() {
                assert_eq!(cell, scalar(q2[k], p2[k]), "{} {}", q2[k], p2[k]);
                assert_eq!(cell, g.cell_of(q2[k], p2[k]));
                if cell.is_some() {
                    inside += 1;
                } else {
                    outside += 1;
                }
            }
        }
        assert!(inside > 4_000 && outside > 500, "{inside} {outside}");
    }

    #[test]
    fn the_papers_grid_has_121548_compatible_cells() {
        assert_eq!(paper_grid().compatible_count(), 121_548);
    }

    /// The compatible cells of `g` in index order (q2 outer, p2 inner).
    fn compatible_in_index_order(g: &Grid) -> Vec<u32> {
        (0..g.cells() as u32)
            .filter(|&c| g.is_compatible(c))
            .collect()
    }

    #[test]
    fn the_default_order_is_a_raster_scan_whatever_the_tiles() {
        for tile in [(1, 1), (2, 3), (5, 4), (3, 2)] {
            let g = Grid::new(0.125, 5, 4, (-0.43, 0.67), (-0.5, 0.5), tile);
            assert_eq!(g.order, ScanOrder::Q2Outer);
            assert_eq!(g.canonical(), &compatible_in_index_order(&g)[..]);
            for (pos, &c) in g.canonical().iter().enumerate() {
                assert_eq!(g.position(c), Some(pos));
            }
        }
    }

    #[test]
    fn tiles_cut_the_canonical_order_into_runs_of_the_tile_size() {
        for order in [
            ScanOrder::Q2Outer,
            ScanOrder::P2OuterReversed,
            ScanOrder::Shuffle(5),
        ] {
            let g = Grid::with_order(0.125, 7, 6, (-0.43, 0.67), (-0.5, 0.5), (2, 3), order);
            let n = g.compatible_count();
            assert!(n > 6 && !n.is_multiple_of(6), "{n}: the last tile is short");
            assert_eq!(g.tile_count(), n.div_ceil(6));
            let joined: Vec<u32> = (0..g.tile_count())
                .flat_map(|t| g.tile_cells(t).to_vec())
                .collect();
            assert_eq!(joined, g.canonical());
            assert_eq!(g.tile_cells(g.tile_count() - 1).len(), n % 6);
            for t in 0..g.tile_count() {
                assert!(g.tile_cells(t).iter().all(|&c| g.tile_of(c) == Some(t)));
            }
            let outside = (0..g.cells() as u32)
                .find(|&c| !g.is_compatible(c))
                .unwrap();
            assert_eq!(g.tile_of(outside), None);
        }
    }

    #[test]
    fn every_scan_order_is_a_permutation_of_the_compatible_cells() {
        let grid = |order| Grid::with_order(0.125, 7, 6, (-0.43, 0.67), (-0.5, 0.5), (3, 4), order);
        let raster = compatible_in_index_order(&grid(ScanOrder::Q2Outer));
        let p2_outer: Vec<u32> = (0..6)
            .flat_map(|j| (0..7).map(move |i| (i * 6 + j) as u32))
            .filter(|c| raster.contains(c))
            .collect();
        let reversed = |v: &[u32]| v.iter().rev().copied().collect::<Vec<u32>>();
        assert_eq!(grid(ScanOrder::P2Outer).canonical(), &p2_outer[..]);
        assert_eq!(
            grid(ScanOrder::Q2OuterReversed).canonical(),
            &reversed(&raster)[..]
        );
        assert_eq!(
            grid(ScanOrder::P2OuterReversed).canonical(),
            &reversed(&p2_outer)[..]
        );
        let shuffled = grid(ScanOrder::Shuffle(7));
        assert_eq!(
            shuffled.canonical(),
            grid(ScanOrder::Shuffle(7)).canonical()
        );
        assert_ne!(
            shuffled.canonical(),
            grid(ScanOrder::Shuffle(8)).canonical()
        );
        assert_ne!(shuffled.canonical(), &raster[..]);
        let mut sorted = shuffled.canonical().to_vec();
        sorted.sort_unstable();
        assert_eq!(sorted, raster);
        for (pos, &c) in shuffled.canonical().iter().enumerate() {
            assert_eq!(shuffled.position(c), Some(pos));
        }
        for name in ScanOrder::NAMES {
            assert_eq!(ScanOrder::from_name(name, 3).unwrap().name(), name);
        }
        assert_eq!(ScanOrder::from_name("spiral", 3), None);
    }

    #[test]
    fn points_map_to_the_cells_that_contain_them() {
        let g = paper_grid();
        for cell in [0u32, 399, 400, 80_199, 159_999] {
            let (q, p) = g.centre(cell);
            assert_eq!(g.cell_of(q, p), Some(cell));
        }
        assert_eq!(g.cell_of(-0.45, 0.0), None);
        assert_eq!(g.cell_of(0.0, 0.5), None);
    }
}
