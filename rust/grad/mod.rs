//! The training kernels: networks with a hand-written reverse pass.
//!
//! `TermsKernel::forward` computes what `delan.Lagrangian.factor_terms` computes (L, H = L Lᵀ, c, g: the inertia
//! network with its q-tangents carried forward, the potential's gradient by one pass down), optionally keeping a `Tape`;
//! `TermsKernel::backward` takes the gradients of a loss with respect to L, H, c and g and returns those with
//! respect to every weight, q, q̇ and z. `MlpKernel` does the same for a plain tanh MLP (the black-box heads,
//! the learned insole mapping). Written out by hand, layer by layer (`net.rs`), per group of samples at the
//! head (`head.rs`), on one matrix product (`gemm.rs`): no autograd graph, no tensor per elementwise op, and
//! every layer's product fused over the value and tangent streams of a tile of samples.
//!
//! Samples go in tiles of `TILE`, tiles in chunks of `CHUNK_TILES`; chunks run on the pool's threads. Each
//! chunk sums its weight gradients apart and the chunks' sums are added in chunk order, so the result is the
//! same bit for bit at any thread count.


pub(crate) mod gemm;
mod dispatch;
mod head;
mod mlp;
mod net;
mod potential;
mod tape;
mod terms;

pub use dispatch::KernelReal;
pub use mlp::MlpKernel;
pub use tape::Tape;
pub use terms::TermsKernel;

use crate::error::{Error, Result};
use crate::real::Real;
use net::{Layer, Net};

/// Samples per tile: a tile's activations stay in the core's caches through a layer's three products.
pub const TILE: usize = 32;
/// Tiles per chunk, the unit of parallel work and of the fixed-order gradient sum.
pub const CHUNK_TILES: usize = 8;

/// One network's weights as torch stores them: per layer (W: out × in row-major, b: out, out, in).
pub type LayerRef<'a, T> = (&'a [T], &'a [T], usize, usize);


/// Weight gradients of one network, in torch's layout: per layer (dW out × in, db out).
pub type NetGrads<T> = Vec<(Vec<T>, Vec<T>)>;

fn check_net<T: Real>(name: &str, layers: &[LayerRef<T>], d_in: usize, d_out: usize) -> Result<Net<T>> {
    if layers.len() < 2 {
        return Err(Error::InputShape(format!("the {name} network needs a hidden layer and an output layer, got {} layers", layers.len())));
    }
    let mut inp = d_in;
    for (i, &(w, b, out, lin)) in layers.iter().enumerate() {
        if lin != inp || w.len() != out * lin || b.len() != out {
            return Err(Error::InputShape(format!(
                "{name} layer {i}: W has {} values and b {} for out {out} x in {lin}; expected in {inp}", w.len(), b.len())));
        }
        inp = out;
    }
    if inp != d_out {
        return Err(Error::InputShape(format!("the {name} network has {inp} outputs, expected {d_out}")));
    }
    Ok(Net { layers: layers.iter().map(|&(w, b, out, inp)| Layer::new(w, b, out, inp)).collect() })
}

/// A gradient buffer's padded blocks back in torch's layout.
fn unpad<T: Real>(net: &Net<T>, g: &[T]) -> NetGrads<T> {
    let mut off = 0;
    net.layers.iter().map(|l| {
        let dw = (0..l.out).flat_map(|o| g[off + o * l.ip..off + o * l.ip + l.inp].iter().copied()).collect();
        let db = g[off + l.op * l.ip..off + l.op * l.ip + l.out].to_vec();
        off += l.grad_len();
        (dw, db)
    }).collect()
}


/// The chunks' weight gradients (`partial`, `len` values each) summed in chunk order: the same bits at any
/// thread count, since a chunk's share does not depend on which thread ran it.
pub(crate) fn sum_chunks<T: Real>(partial: &[T], len: usize) -> Vec<T> {
    let mut total = vec![T::default(); len];
    for part in partial.chunks_exact(len.max(1)) {
        for (t, p) in total.iter_mut().zip(part) {
            *t = *t + *p;
        }
    }
    total
}

#[cfg(test)]
mod tests;
