//! The grid of cells on the surface of section q1 = 0, p1 > 0, its tiles and canonical order.

use salient_core::section::{p1_squared, CellLattice};
use salient_core::HenonHeiles;

/// A rectangular grid over (q2, p2) with its compatible cells in canonical order.
#[derive(Clone, Debug, PartialEq)]
pub struct Grid {
    pub energy: f64,
    pub n_q2: usize,
    pub n_p2: usize,
    pub q2: (f64, f64),
    pub p2: (f64, f64),
    /// Tile size in cells along q2 and p2.
    pub tile: (usize, usize),
    compatible: Vec<bool>,
    /// [`Grid::spacing`], computed once: the cell of every crossing divides by it.
    step: (f64, f64),
    /// Compatible cells in canonical order: tiles in raster order (q2 tile index outer), and
    /// cells inside a tile in raster order (i outer, j inner).
    canonical: Vec<u32>,
    /// Canonical position of each compatible cell (u32::MAX for the others).
    position: Vec<u32>,
}

impl Grid {
    /// A grid of `n_q2 × n_p2` cells over the given bounds, split into tiles of `tile` cells.
    /// A cell is compatible when its centre lies on the section (p1² > 0).
    pub fn new(
        energy: f64,
        n_q2: usize,
        n_p2: usize,
        q2: (f64, f64),
        p2: (f64, f64),
        tile: (usize, usize),
    ) -> Self {
        assert!(n_q2 > 0 && n_p2 > 0 && tile.0 > 0 && tile.1 > 0);
        assert!(n_q2 * n_p2 <= u32::MAX as usize / 2);
        let mut g = Grid {
            energy,
            n_q2,
            n_p2,
            q2,
            p2,
            tile,
            step: ((q2.1 - q2.0) / n_q2 as f64, (p2.1 - p2.0) / n_p2 as f64),
            compatible: vec![false; n_q2 * n_p2],
            canonical: Vec::new(),
            position: vec![u32::MAX; n_q2 * n_p2],
        };
        for cell in 0..n_q2 * n_p2 {
            let (x, y) = g.centre(cell as u32);
            g.compatible[cell] = p1_squared(&HenonHeiles, energy, &[0.0, x], &[0.0, y]) > 0.0;
        }
        for ti in 0..n_q2.div_ceil(tile.0) {
            for tj in 0..n_p2.div_ceil(tile.1) {
                let cells: Vec<u32> = g.tile_cells(ti, tj).collect();
                for cell in cells {
                    if g.compatible[cell as usize] {
                        g.position[cell as usize] = g.canonical.len() as u32;
                        g.canonical.push(cell);
                    }
                }
            }
        }
        g
    }

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

    pub fn is_compatible(&self, cell: u32) -> bool {
        self.compatible[cell as usize]
    }

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

    /// Number of tiles along q2 and p2.
    pub fn tiles(&self) -> (usize, usize) {
        (
            self.n_q2.div_ceil(self.tile.0),
            self.n_p2.div_ceil(self.tile.1),
        )
    }

    /// Number of tiles; a tile's index counts them in raster order (q2 tile index outer), the
    /// order in which the canonical order visits them.
    pub fn tile_count(&self) -> usize {
        let (a, b) = self.tiles();
        a * b
    }

    /// The index of the tile holding `cell`.
    pub fn tile_of(&self, cell: u32) -> usize {
        let (i, j) = self.ij(cell);
        (i / self.tile.0) * self.tiles().1 + j / self.tile.1
    }

    /// The compatible cells of tile `index`, in canonical order.
    pub fn tile_compatible_cells(&self, index: usize) -> impl Iterator<Item = u32> + '_ {
        let nj = self.tiles().1;
        self.tile_cells(index / nj, index % nj)
            .filter(|&c| self.is_compatible(c))
    }

    /// The cells of tile (ti, tj) in raster order (compatible or not).
    pub fn tile_cells(&self, ti: usize, tj: usize) -> impl Iterator<Item = u32> + '_ {
        let (i0, j0) = (ti * self.tile.0, tj * self.tile.1);
        let (i1, j1) = (
            (i0 + self.tile.0).min(self.n_q2),
            (j0 + self.tile.1).min(self.n_p2),
        );
        (i0..i1).flat_map(move |i| (j0..j1).map(move |j| self.index(i, j)))
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

    #[test]
    fn canonical_order_is_tile_major_then_raster() {
        let g = Grid::new(0.125, 5, 4, (-0.43, 0.67), (-0.5, 0.5), (2, 3));
        let mut all = Vec::new();
        for ti in 0..3 {
            for tj in 0..2 {
                all.extend(g.tile_cells(ti, tj).filter(|&c| g.is_compatible(c)));
            }
        }
        assert_eq!(g.canonical(), &all[..]);
        // The first tile is rows i = 0, 1 and columns j = 0..3.
        let first: Vec<u32> = g.tile_cells(0, 0).collect();
        assert_eq!(first, vec![0, 1, 2, 4, 5, 6]);
        for (pos, &c) in g.canonical().iter().enumerate() {
            assert_eq!(g.position(c), Some(pos));
        }
        // Tile indices count tiles in raster order, and the tiles' compatible cells in index
        // order are the canonical order.
        assert_eq!(g.tile_count(), 6);
        let by_index: Vec<u32> = (0..6).flat_map(|t| g.tile_compatible_cells(t)).collect();
        assert_eq!(g.canonical(), &by_index[..]);
        assert_eq!(g.tile_of(6), 0);
        assert_eq!(g.tile_of(7), 1);
        assert_eq!(g.tile_of(g.index(4, 3)), 5);
        for t in 0..6 {
            assert!(g.tile_compatible_cells(t).all(|c| g.tile_of(c) == t));
        }
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
