//! A plain tanh MLP (tanh hidden layers, a linear output layer) and its reverse pass: the networks that carry no
//! q-tangents (the black-box models' heads, the learned insole mapping), on the terms kernel's tiles and
//! products with one stream per tile.

use super::dispatch::KernelReal;
use super::net::{self, BackBufs, Net, Tile};
use super::tape::Tape;
use super::{check_net, sum_chunks, unpad, LayerRef, NetGrads, CHUNK_TILES, TILE};
use crate::error::{Error, Result};
use crate::pool::{Chunks, Pool};
use crate::real::Real;
use crate::simd::Simd;

/// A tanh MLP's prepared weights.
pub struct MlpKernel<T> {
    net: Net<T>,
    d_in: usize,
    d_out: usize,
    simd: Simd,
}

impl<T: KernelReal> MlpKernel<T> {
    /// Prepare the layers (torch's layout; at least one hidden layer).
    pub fn new(layers: &[LayerRef<T>]) -> Result<MlpKernel<T>> {
        let (Some(first), Some(last)) = (layers.first(), layers.last()) else {
            return Err(Error::InputShape("an MLP needs layers".into()));
        };
        let (d_in, d_out) = (first.3, last.2);
        Ok(MlpKernel { net: check_net("mlp", layers, d_in, d_out)?, d_in, d_out, simd: crate::simd::detect() })
    }

    /// (out, in) of every layer.
    pub fn shapes(&self) -> Vec<(usize, usize)> {
        self.net.layers.iter().map(|l| (l.out, l.inp)).collect()
    }

    /// y (N × d_out) at x (N × d_in); with `tape`, what the reverse pass needs is kept there.
    pub fn forward(&self, x: &[T], y: &mut [T], tape: Option<&mut Tape<T>>, pool: &Pool) -> Result<()> {
        let samples = x.len() / self.d_in.max(1);
        if x.len() != samples * self.d_in || y.len() != samples * self.d_out {
            return Err(Error::InputShape(format!("mlp forward: x has {} values and y {} for {} in, {} out",
                                                 x.len(), y.len(), self.d_in, self.d_out)));
        }
        let tiles = samples.div_ceil(TILE);
        let tl = self.tile_len();
        let mut none = Vec::new();
        let (data, keep): (&mut [T], bool) = match tape {
            Some(t) => (t.prepare(samples, tiles * tl), true),
            None => (&mut none, false),
        };
        let outs = (Chunks::new(data, CHUNK_TILES * tl), Chunks::new(y, CHUNK_TILES * TILE * self.d_out));
        let job = MlpFwd { k: self, x, samples, keep };
        pool.run(tiles.div_ceil(CHUNK_TILES), &|ci| {
            // SAFETY: each chunk index is taken by one task only.
            let (tp, yo) = unsafe { (outs.0.get(ci), outs.1.get(ci)) };
            T::mlp_forward_chunk(self.simd, &job, ci, tp, yo);
        });
        Ok(())
    }

    /// The reverse pass over a tape of `forward`: dy (N × d_out) in, dx (N × d_in) out where given, and the
    /// weight gradients (torch's layout).
    pub fn backward(&self, tape: &Tape<T>, dy: &[T], dx: Option<&mut [T]>, pool: &Pool) -> Result<NetGrads<T>> {
        let samples = tape.samples;
        let tiles = samples.div_ceil(TILE);
        if tape.data.len() != tiles * self.tile_len() || dy.len() != samples * self.d_out
            || dx.as_ref().is_some_and(|d| d.len() != samples * self.d_in) {
            return Err(Error::InputShape(format!("mlp backward: inconsistent lengths for {samples} samples")));
        }
        let chunks = tiles.div_ceil(CHUNK_TILES);
        let gl = self.net.grad_len();
        let mut partial = vec![T::default(); chunks * gl];
        let want_dx = dx.is_some();
        let mut no_dx = Vec::new();
        let dx = dx.unwrap_or(&mut no_dx);
        {
            let outs = (Chunks::new(&mut partial, gl), Chunks::new(dx, CHUNK_TILES * TILE * self.d_in));
            let job = MlpBwd { k: self, tape, dy, want_dx };
            pool.run(chunks, &|ci| {
                // SAFETY: each chunk index is taken by one task only.
                let (pg, d) = unsafe { (outs.0.get(ci), outs.1.get(ci)) };
                T::mlp_backward_chunk(self.simd, &job, ci, pg, d);
            });
        }
        Ok(unpad(&self.net, &sum_chunks(&partial, gl)))
    }
}

impl<T: Real> MlpKernel<T> {
    /// Values of one tile's tape: its input x, then the network's blocks.
    fn tile_len(&self) -> usize {
        TILE * self.net.layers[0].ip + self.net.tape_len(TILE)
    }
}

#[doc(hidden)]
pub struct MlpFwd<'a, T> {
    k: &'a MlpKernel<T>,
    x: &'a [T],
    samples: usize,
    keep: bool,
}

#[doc(hidden)]
pub struct MlpBwd<'a, T: KernelReal> {
    k: &'a MlpKernel<T>,
    tape: &'a Tape<T>,
    dy: &'a [T],
    want_dx: bool,
}

#[inline(always)]
pub(super) fn forward_chunk<T: Real, const FMA: bool, const WIDE: bool>(job: &MlpFwd<T>, ci: usize, tape: &mut [T], y: &mut [T]) {
    let k = job.k;
    let (ip0, tl, d_in, d_out) = (k.net.layers[0].ip, k.tile_len(), k.d_in, k.d_out);
    let opo = k.net.layers.last().unwrap().op;
    let mut own = if job.keep { Vec::new() } else { vec![T::default(); tl] };
    let first_tile = ci * CHUNK_TILES;
    let tiles = (job.samples.div_ceil(TILE) - first_tile).min(CHUNK_TILES);
    for ti in 0..tiles {
        let first = (first_tile + ti) * TILE;
        let count = (job.samples - first).min(TILE);
        let tt = if job.keep { &mut tape[ti * tl..(ti + 1) * tl] } else { &mut own[..] };
        let (x, nt) = tt.split_at_mut(TILE * ip0);
        x.fill(T::default());
        for r in 0..count {
            x[r * ip0..r * ip0 + d_in].copy_from_slice(&job.x[(first + r) * d_in..(first + r + 1) * d_in]);
        }
        let tile = Tile { t: TILE, s: 1, x, dphi: &[], cols: &[] };
        net::forward::<T, FMA, WIDE>(&k.net, &tile, nt);
        let out = &nt[k.net.out_offset(TILE)..];
        for r in 0..count {
            let e = ti * TILE + r;
            y[e * d_out..(e + 1) * d_out].copy_from_slice(&out[r * opo..r * opo + d_out]);
        }
    }
}

#[inline(always)]
pub(super) fn backward_chunk<T: KernelReal, const FMA: bool, const WIDE: bool>(job: &MlpBwd<T>, ci: usize, grad: &mut [T], dx: &mut [T]) {
    let k = job.k;
    let (ip0, tl, d_in, d_out) = (k.net.layers[0].ip, k.tile_len(), k.d_in, k.d_out);
    let opo = k.net.layers.last().unwrap().op;
    let samples = job.tape.samples;
    let mut bufs = BackBufs::new(TILE * k.net.width());
    let mut gx = vec![T::default(); TILE * ip0];
    let mut no_tangents: [T; 0] = [];
    let first_tile = ci * CHUNK_TILES;
    let tiles = (samples.div_ceil(TILE) - first_tile).min(CHUNK_TILES);
    for ti in 0..tiles {
        let first = (first_tile + ti) * TILE;
        let count = (samples - first).min(TILE);
        let (x, nt) = job.tape.data[(first_tile + ti) * tl..(first_tile + ti + 1) * tl].split_at(TILE * ip0);
        let tile = Tile { t: TILE, s: 1, x, dphi: &[], cols: &[] };
        bufs.g[..TILE * opo].fill(T::default());
        for r in 0..count {
            bufs.g[r * opo..r * opo + d_out].copy_from_slice(&job.dy[(first + r) * d_out..(first + r + 1) * d_out]);
        }
        gx.fill(T::default());
        net::backward::<T, FMA, WIDE>(&k.net, &tile, nt, &mut bufs, grad, &mut gx, &mut no_tangents);
        if job.want_dx {
            for r in 0..count {
                let e = ti * TILE + r;
                dx[e * d_in..(e + 1) * d_in].copy_from_slice(&gx[r * ip0..r * ip0 + d_in]);
            }
        }
    }
}
