//! Per sample, from the networks' outputs to the rigid-body terms and back: the Cholesky factor L
//! (softplus + offset on the diagonal), H = L Lᵀ, c = Ḣ q̇ − ½ ∂(q̇ᵀ H q̇)/∂q and g = ∂V/∂q, and the
//! reverse of each step. The same formulas as `delan.Lagrangian.factor_terms` (python/exolan/delan.py).

use std::ops::{Add, Mul, Neg, Sub};

use crate::real::Real;

/// The arithmetic the head needs: a float (`Real`), or `Lanes` of them, so that one tile's samples go
/// through the head side by side in vector registers.
pub(crate) trait Num: Copy + Default + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Neg<Output = Self> {
    fn of(x: f64) -> Self;
    fn softplus_sigmoid(self) -> (Self, Self);
}

impl<T: Real> Num for T {
    #[inline(always)]
    fn of(x: f64) -> T {
        <T as Real>::of(x)
    }
    #[inline(always)]
    fn softplus_sigmoid(self) -> (T, T) {
        <T as Real>::softplus_sigmoid(self)
    }
}

/// L samples' values of one quantity, operated on lane by lane.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Lanes<T, const L: usize>(pub [T; L]);

impl<T: Real, const L: usize> Default for Lanes<T, L> {
    #[inline(always)]
    fn default() -> Self {
        Lanes([T::default(); L])
    }
}

macro_rules! lane_op {
    ($tr:ident, $f:ident, $op:tt) => {
        impl<T: Real, const L: usize> $tr for Lanes<T, L> {
            type Output = Self;
            #[inline(always)]
            fn $f(self, o: Self) -> Self {
                let mut r = self.0;
                for l in 0..L {
                    r[l] = self.0[l] $op o.0[l];
                }
                Lanes(r)
            }
        }
    };
}
lane_op!(Add, add, +);
lane_op!(Sub, sub, -);
lane_op!(Mul, mul, *);

impl<T: Real, const L: usize> Neg for Lanes<T, L> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        let mut r = self.0;
        for l in 0..L {
            r[l] = -self.0[l];
        }
        Lanes(r)
    }
}

impl<T: Real, const L: usize> Num for Lanes<T, L> {
    #[inline(always)]
    fn of(x: f64) -> Self {
        Lanes([<T as Real>::of(x); L])
    }
    #[inline(always)]
    fn softplus_sigmoid(self) -> (Self, Self) {
        let (mut a, mut b) = (self.0, self.0);
        for l in 0..L {
            (a[l], b[l]) = <T as Real>::softplus_sigmoid(self.0[l]);
        }
        (Lanes(a), Lanes(b))
    }
}

/// Most joints a kernel call handles (the arrays below are sized for it).
pub(crate) const NMAX: usize = 3;
/// Entries of L for NMAX joints.
pub(crate) const MMAX: usize = NMAX * (NMAX + 1) / 2;

type Mat<T> = [[T; NMAX]; NMAX];

/// The inertia network's outputs at one sample: u (diagonal entries first, then the strict lower part
/// row by row: (1,0), (2,0), (2,1)), and their q_k-tangents.
#[derive(Clone, Copy)]
pub(crate) struct Outs<T> {
    pub u: [T; MMAX],
    pub ud: [[T; MMAX]; NMAX],
}

/// L, its q_k-tangents and the diagonal's sigmoid (softplus'), from the network outputs.
struct Factor<T> {
    l: Mat<T>,
    ld: [Mat<T>; NMAX],
    sig: [T; NMAX],
}

fn lower(n: usize) -> impl Iterator<Item = (usize, usize, usize)> {
    (1..n).flat_map(|i| (0..i).map(move |j| (i, j))).enumerate().map(move |(o, (i, j))| (n + o, i, j))
}

#[inline(always)]
fn factor<T: Num>(n: usize, o: &Outs<T>, offset: T) -> Factor<T> {
    let z = T::default();
    let mut f = Factor { l: [[z; NMAX]; NMAX], ld: [[[z; NMAX]; NMAX]; NMAX], sig: [z; NMAX] };
    for i in 0..n {
        let (sp, sg) = o.u[i].softplus_sigmoid();
        f.l[i][i] = sp + offset;
        f.sig[i] = sg;
        for k in 0..n {
            f.ld[k][i][i] = sg * o.ud[k][i];
        }
    }
    for (e, i, j) in lower(n) {
        f.l[i][j] = o.u[e];
        for k in 0..n {
            f.ld[k][i][j] = o.ud[k][e];
        }
    }
    f
}

/// The intermediate vectors of c: w = Lᵀ q̇, Ld = Σ_k q̇_k ∂L/∂q_k, v = Ldᵀ q̇.
struct Coriolis<T> {
    w: [T; NMAX],
    ldq: Mat<T>,
    v: [T; NMAX],
}

#[inline(always)]
fn coriolis_parts<T: Num>(n: usize, f: &Factor<T>, qd: &[T]) -> Coriolis<T> {
    let z = T::default();
    let mut p = Coriolis { w: [z; NMAX], ldq: [[z; NMAX]; NMAX], v: [z; NMAX] };
    for i in 0..n {
        for j in 0..=i {
            let mut s = z;
            for k in 0..n {
                s = s + qd[k] * f.ld[k][i][j];
            }
            p.ldq[i][j] = s;
        }
    }
    for j in 0..n {
        for i in j..n {
            p.w[j] = p.w[j] + f.l[i][j] * qd[i];
            p.v[j] = p.v[j] + p.ldq[i][j] * qd[i];
        }
    }
    p
}

/// Forward: L (n×n, row-major, zeros above the diagonal), H, c and g of one sample; `gv[k]` is the
/// potential network's q_k-derivative (g = v_scale · gv).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn forward<T: Num>(n: usize, o: &Outs<T>, gv: &[T], qd: &[T], offset: T, v_scale: T,
                               l_out: &mut [T], h_out: &mut [T], c_out: &mut [T], g_out: &mut [T]) {
    let f = factor(n, o, offset);
    let p = coriolis_parts(n, &f, qd);
    for i in 0..n {
        for j in 0..n {
            l_out[i * n + j] = f.l[i][j];
            let mut s = T::default();
            for k in 0..=i.min(j) {
                s = s + f.l[i][k] * f.l[j][k];
            }
            h_out[i * n + j] = s;
        }
        // c_i = (Ld w + L v)_i − q̇ᵀ (∂L/∂q_i) w
        let mut s = T::default();
        for j in 0..=i {
            s = s + p.ldq[i][j] * p.w[j] + f.l[i][j] * p.v[j];
        }
        let mut dt = T::default();
        for a in 0..n {
            for b in 0..=a {
                dt = dt + qd[a] * f.ld[i][a][b] * p.w[b];
            }
        }
        c_out[i] = s - dt;
        g_out[i] = v_scale * gv[i];
    }
}

/// The gradients a sample's head sends back: to the inertia network's outputs and tangents, to the
/// potential network's q-derivatives, and to q̇.
pub(crate) struct Back<T> {
    pub u: [T; MMAX],
    pub ud: [[T; MMAX]; NMAX],
    pub gv: [T; NMAX],
    pub qd: [T; NMAX],
}

/// Reverse of `forward` for upstream gradients of L, H, c, g (n×n, n×n, n, n; entries above L's
/// diagonal are ignored: they are structural zeros).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn backward<T: Num>(n: usize, o: &Outs<T>, qd: &[T], offset: T, v_scale: T,
                                dl: &[T], dh: &[T], dc: &[T], dg: &[T]) -> Back<T> {
    let z = T::default();
    let f = factor(n, o, offset);
    let p = coriolis_parts(n, &f, qd);
    let mut lb: Mat<T> = [[z; NMAX]; NMAX];
    let mut ldb: [Mat<T>; NMAX] = [[[z; NMAX]; NMAX]; NMAX];
    let mut ldqb: Mat<T> = [[z; NMAX]; NMAX];
    let (mut wb, mut vb, mut qdb) = ([z; NMAX], [z; NMAX], [z; NMAX]);
    // c = Ld w + L v − dT, dT_k = q̇ᵀ (∂L/∂q_k) w
    for i in 0..n {
        for j in 0..=i {
            ldqb[i][j] = dc[i] * p.w[j];
            wb[j] = wb[j] + p.ldq[i][j] * dc[i];
            lb[i][j] = dc[i] * p.v[j];
            vb[j] = vb[j] + f.l[i][j] * dc[i];
        }
    }
    for k in 0..n {
        let dtb = -dc[k];
        for a in 0..n {
            for b in 0..=a {
                ldb[k][a][b] = dtb * qd[a] * p.w[b];
                qdb[a] = qdb[a] + dtb * f.ld[k][a][b] * p.w[b];
                wb[b] = wb[b] + dtb * qd[a] * f.ld[k][a][b];
            }
        }
    }
    // v = Ldᵀ q̇
    for j in 0..n {
        for i in j..n {
            ldqb[i][j] = ldqb[i][j] + vb[j] * qd[i];
            qdb[i] = qdb[i] + p.ldq[i][j] * vb[j];
        }
    }
    // Ld = Σ_k q̇_k ∂L/∂q_k
    for k in 0..n {
        for i in 0..n {
            for j in 0..=i {
                ldb[k][i][j] = ldb[k][i][j] + qd[k] * ldqb[i][j];
                qdb[k] = qdb[k] + ldqb[i][j] * f.ld[k][i][j];
            }
        }
    }
    // w = Lᵀ q̇; H = L Lᵀ; L itself
    for i in 0..n {
        for j in 0..=i {
            lb[i][j] = lb[i][j] + qd[i] * wb[j];
            qdb[i] = qdb[i] + f.l[i][j] * wb[j];
            let mut s = dl[i * n + j];
            for a in 0..n {
                s = s + (dh[i * n + a] + dh[a * n + i]) * f.l[a][j];
            }
            lb[i][j] = lb[i][j] + s;
        }
    }
    // L's entries from the network outputs: softplus' = σ on the diagonal, σ' = σ(1 − σ) for its tangents
    let one = T::of(1.0);
    let mut back = Back { u: [z; MMAX], ud: [[z; MMAX]; NMAX], gv: [z; NMAX], qd: qdb };
    for i in 0..n {
        let (sg, dsg) = (f.sig[i], f.sig[i] * (one - f.sig[i]));
        let mut s = lb[i][i] * sg;
        for k in 0..n {
            s = s + ldb[k][i][i] * dsg * o.ud[k][i];
            back.ud[k][i] = ldb[k][i][i] * sg;
        }
        back.u[i] = s;
    }
    for (e, i, j) in lower(n) {
        back.u[e] = lb[i][j];
        for k in 0..n {
            back.ud[k][e] = ldb[k][i][j];
        }
    }
    for k in 0..n {
        back.gv[k] = v_scale * dg[k];
    }
    back
}
