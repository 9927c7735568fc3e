//! Flat-shell triangle for a non-axisymmetric eardrum: constant-strain membrane (CST) plus
//! discrete Kirchhoff bending (DKT, Batoz, Bathe & Ho 1980, Int J Numer Meth Eng
//! 15:1771), with a small drilling stiffness, 6 DOFs per node in global axes.
//!
//! Node DOFs (global): [u_x, u_y, u_z, θ_x, θ_y, θ_z], rotations as right-handed rotation
//! vectors, so a small rigid rotation ω moves a point r by ω × r.
//!
//! In the element's own frame (e1 along edge 0→1, e3 the unit normal (p1−p0)×(p2−p0),
//! e2 = e3 × e1) the membrane takes (u, v), bending takes (w, θ_x, θ_y) with the slopes
//! w,x = −θ_y and w,y = θ_x, and θ_z gets a drilling spring. DKT is built here from its
//! definition rather than from the explicit Batoz formulas: the rotations of the normal
//! (β_x, β_y) = (w,x, w,y) are quadratic over the six-node triangle; at the corners they
//! equal the nodal slopes; at each mid-side the tangential slope is that of the cubic
//! Hermite interpolant of w along the edge and the normal slope is the mean of the two
//! corners'. Curvatures (β_x,x, β_y,y, β_x,y + β_y,x) are linear, so the three mid-side
//! points integrate the bending energy exactly.
//!
//! Every stiffness is for E = 1 Pa (the element is linear in E, so the assembled K = E·K_unit
//! and the drum's modes do not depend on E). Mass: consistent linear interpolation for the
//! translations (ρhA/12·(1 + δ_ij) per component) plus a lumped rotary inertia ρh³/12·A/3
//! per rotation DOF; both are isotropic, so they are the same in every frame. Pressure
//! load and swept volume: the translation of each node along the normal, weight A/3 (exact
//! for any rigid translation: the volume is the projected area times the displacement).

/// Material and thickness of a shell part (same meaning as [`super::shell::ShellMaterial`]).
pub use super::shell::ShellMaterial;

/// Drilling stiffness per unit E, as a fraction of the bending rigidity h³/(12(1 − ν²)):
/// k_drill = α·D·[[1, −½, −½], [−½, 1, −½], [−½, −½, 1]] on the three nodes' rotations about
/// the normal (a rigid rotation about the normal costs nothing). Small enough to leave the
/// hemisphere's membrane answer unchanged (a test varies it ×100).
pub const DRILL_ALPHA: f64 = 1e-2;

/// One triangle's matrices in global DOFs [node 0 (6), node 1 (6), node 2 (6)].
#[derive(Clone, Debug)]
pub struct TriShell {
    /// Stiffness for E = 1 Pa.
    pub k_unit: [[f64; 18]; 18],
    /// Mass (consistent translations, lumped rotary inertia).
    pub m: [[f64; 18]; 18],
    /// Swept volume per DOF (= load of a unit pressure on the side the normal points
    /// away from): volume = bᵀq.
    pub b: [f64; 18],
    /// Area, m².
    pub area: f64,
    /// Unit normal (p1 − p0) × (p2 − p0) / 2A.
    pub normal: [f64; 3],
}

type V3 = [f64; 3];

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross(a: V3, b: V3) -> V3 {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn unit(a: V3) -> V3 {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

/// Membrane (CST) stiffness per unit E in local DOFs [u0, v0, u1, v1, u2, v2].
pub fn cst_membrane(xy: [(f64, f64); 3], h: f64, nu: f64) -> [[f64; 6]; 6] {
    let (area, dl) = area_gradients(xy);
    // ε = (u,x, v,y, u,y + v,x)
    let mut bm = [[0.0; 6]; 3];
    for i in 0..3 {
        bm[0][2 * i] = dl[i].0;
        bm[1][2 * i + 1] = dl[i].1;
        bm[2][2 * i] = dl[i].1;
        bm[2][2 * i + 1] = dl[i].0;
    }
    btdb(&bm, &plane_stress(nu), h * area / (1.0 - nu * nu))
}

/// DKT bending stiffness per unit E in local DOFs [w0, θx0, θy0, w1, θx1, θy1, w2, θx2, θy2].
pub fn dkt_bending(xy: [(f64, f64); 3], h: f64, nu: f64) -> [[f64; 9]; 9] {
    let (area, dl) = area_gradients(xy);
    let d = h.powi(3) / (12.0 * (1.0 - nu * nu));
    let tdof = dkt_rotations(xy);
    let dmat = plane_stress(nu);
    let mut k = [[0.0; 9]; 9];
    // Mid-side points of the triangle, weight A/3 each: exact for the quadratic integrand.
    for q in 0..3 {
        let mut lq = [0.5; 3];
        lq[(q + 2) % 3] = 0.0;
        let dn = quadratic_gradients(lq, dl);
        // κ = (β_x,x, β_y,y, β_x,y + β_y,x) = Bβ · β
        let mut bb = [[0.0; 9]; 3];
        for node in 0..6 {
            for c in 0..9 {
                let (bx, by) = (tdof[2 * node][c], tdof[2 * node + 1][c]);
                bb[0][c] += dn[node].0 * bx;
                bb[1][c] += dn[node].1 * by;
                bb[2][c] += dn[node].1 * bx + dn[node].0 * by;
            }
        }
        let kq = btdb(&bb, &dmat, d * area / 3.0);
        for i in 0..9 {
            for j in 0..9 {
                k[i][j] += kq[i][j];
            }
        }
    }
    k
}

/// DKT's kinematics: the normal's rotations (β_x, β_y) at the six quadratic nodes
/// (corners 0..3, then mid-sides of edges (0,1), (1,2), (2,0); rows 2·node + {0: β_x,
/// 1: β_y}) from the element's DOFs [w, θ_x, θ_y] per corner. Kept apart from the
/// integration because this is where the Kirchhoff constraints live.
fn dkt_rotations(xy: [(f64, f64); 3]) -> [[f64; 9]; 12] {
    // T: nodal (w, w,x, w,y) → (β_x, β_y) at the six nodes.
    let mut t = [[0.0; 9]; 12];
    for i in 0..3 {
        t[2 * i][3 * i + 1] = 1.0;
        t[2 * i + 1][3 * i + 2] = 1.0;
    }
    for k in 0..3 {
        let (i, j) = (k, (k + 1) % 3);
        let (dx, dy) = (xy[j].0 - xy[i].0, xy[j].1 - xy[i].1);
        let l = (dx * dx + dy * dy).sqrt();
        let (s, n) = ((dx / l, dy / l), (dy / l, -dx / l));
        // tangential slope at mid-side: 3(w_j − w_i)/(2l) − (s·g_i + s·g_j)/4
        // normal slope: (n·g_i + n·g_j)/2
        let mut ts = [0.0; 9];
        let mut tn = [0.0; 9];
        ts[3 * i] = -1.5 / l;
        ts[3 * j] = 1.5 / l;
        for node in [i, j] {
            ts[3 * node + 1] -= 0.25 * s.0;
            ts[3 * node + 2] -= 0.25 * s.1;
            tn[3 * node + 1] += 0.5 * n.0;
            tn[3 * node + 2] += 0.5 * n.1;
        }
        for c in 0..9 {
            t[2 * (3 + k)][c] = ts[c] * s.0 + tn[c] * n.0;
            t[2 * (3 + k) + 1][c] = ts[c] * s.1 + tn[c] * n.1;
        }
    }
    // Slopes (w,x, w,y) = (−θ_y, θ_x): map the DOF columns.
    let mut tdof = [[0.0; 9]; 12];
    for r in 0..12 {
        for node in 0..3 {
            tdof[r][3 * node] = t[r][3 * node];
            tdof[r][3 * node + 1] = t[r][3 * node + 2]; // θ_x = w,y
            tdof[r][3 * node + 2] = -t[r][3 * node + 1]; // θ_y = −w,x
        }
    }
    tdof
}

/// Gradients (∂N/∂x, ∂N/∂y) of the six quadratic shape functions (corners, then mid-sides
/// of edges (0,1), (1,2), (2,0)) at area coordinates `lq`, from the gradients `dl` of the
/// area coordinates.
fn quadratic_gradients(lq: [f64; 3], dl: [(f64, f64); 3]) -> [(f64, f64); 6] {
    let mut dn = [(0.0, 0.0); 6];
    for i in 0..3 {
        let f = 4.0 * lq[i] - 1.0;
        dn[i] = (f * dl[i].0, f * dl[i].1);
        let (a, b) = (i, (i + 1) % 3);
        dn[3 + i] = (4.0 * (lq[b] * dl[a].0 + lq[a] * dl[b].0), 4.0 * (lq[b] * dl[a].1 + lq[a] * dl[b].1));
    }
    dn
}

/// Area and the gradients (∂L_i/∂x, ∂L_i/∂y) of the area coordinates.
fn area_gradients(xy: [(f64, f64); 3]) -> (f64, [(f64, f64); 3]) {
    let two_a = (xy[1].0 - xy[0].0) * (xy[2].1 - xy[0].1) - (xy[2].0 - xy[0].0) * (xy[1].1 - xy[0].1);
    assert!(two_a > 0.0, "triangle must be counter-clockwise and non-degenerate: {xy:?}");
    let dl = std::array::from_fn(|i| {
        let (j, k) = ((i + 1) % 3, (i + 2) % 3);
        ((xy[j].1 - xy[k].1) / two_a, (xy[k].0 - xy[j].0) / two_a)
    });
    (0.5 * two_a, dl)
}

fn plane_stress(nu: f64) -> [[f64; 3]; 3] {
    [[1.0, nu, 0.0], [nu, 1.0, 0.0], [0.0, 0.0, 0.5 * (1.0 - nu)]]
}

/// scale · Bᵀ D B for a 3×N strain matrix.
fn btdb<const N: usize>(b: &[[f64; N]; 3], d: &[[f64; 3]; 3], scale: f64) -> [[f64; N]; N] {
    let mut db = [[0.0; N]; 3];
    for r in 0..3 {
        for c in 0..N {
            db[r][c] = (0..3).map(|s| d[r][s] * b[s][c]).sum();
        }
    }
    let mut k = [[0.0; N]; N];
    for i in 0..N {
        for j in 0..N {
            k[i][j] = scale * (0..3).map(|r| b[r][i] * db[r][j]).sum::<f64>();
        }
    }
    k
}

impl TriShell {
    /// Element on nodes p0, p1, p2 (global coordinates, m); its normal is
    /// (p1 − p0) × (p2 − p0), so order the nodes counter-clockwise seen from the side the
    /// normal should point to.
    pub fn new(p: [V3; 3], mat: &ShellMaterial) -> TriShell {
        TriShell::with_drill(p, mat, DRILL_ALPHA)
    }

    /// The same with drilling factor `drill` in place of [`DRILL_ALPHA`].
    pub fn with_drill(p: [V3; 3], mat: &ShellMaterial, drill: f64) -> TriShell {
        let e1 = unit(sub(p[1], p[0]));
        let nvec = cross(sub(p[1], p[0]), sub(p[2], p[0]));
        let area = 0.5 * dot(nvec, nvec).sqrt();
        let e3 = unit(nvec);
        let e2 = cross(e3, e1);
        let rot = [e1, e2, e3]; // rows: local axes in global components
        let xy: [(f64, f64); 3] = std::array::from_fn(|i| {
            let d = sub(p[i], p[0]);
            (dot(d, e1), dot(d, e2))
        });
        let (h, nu) = (mat.h, mat.nu);
        let km = cst_membrane(xy, h, nu);
        let kb = dkt_bending(xy, h, nu);
        // Local 18×18: per node [u, v, w, θx, θy, θz].
        let mut kl = [[0.0; 18]; 18];
        let mem = |n: usize, c: usize| 6 * n + c; // c ∈ {0, 1}
        for i in 0..6 {
            for j in 0..6 {
                kl[mem(i / 2, i % 2)][mem(j / 2, j % 2)] += km[i][j];
            }
        }
        for i in 0..9 {
            for j in 0..9 {
                kl[6 * (i / 3) + 2 + i % 3][6 * (j / 3) + 2 + j % 3] += kb[i][j];
            }
        }
        let kd = drill * h.powi(3) / (12.0 * (1.0 - nu * nu));
        for i in 0..3 {
            for j in 0..3 {
                kl[6 * i + 5][6 * j + 5] += kd * if i == j { 1.0 } else { -0.5 };
            }
        }
        // Local = R·global per 3-vector; q_local = T q_global with T = blockdiag(R).
        let mut k_unit = [[0.0; 18]; 18];
        let mut kt = [[0.0; 18]; 18]; // K_local · T
        for (row, kl_row) in kt.iter_mut().zip(&kl) {
            for (j, v) in row.iter_mut().enumerate() {
                let (bj, cj) = (j / 3, j % 3);
                *v = (0..3).map(|s| kl_row[3 * bj + s] * rot[s][cj]).sum();
            }
        }
        for (i, row) in k_unit.iter_mut().enumerate() {
            let (bi, ci) = (i / 3, i % 3);
            for (j, v) in row.iter_mut().enumerate() {
                *v = (0..3).map(|s| rot[s][ci] * kt[3 * bi + s][j]).sum();
            }
        }
        let mut m = [[0.0; 18]; 18];
        let mt = mat.rho * h * area / 12.0;
        let mr = mat.rho * h.powi(3) / 12.0 * area / 3.0;
        for i in 0..3 {
            for j in 0..3 {
                for c in 0..3 {
                    m[6 * i + c][6 * j + c] = mt * if i == j { 2.0 } else { 1.0 };
                }
            }
            for c in 3..6 {
                m[6 * i + c][6 * i + c] = mr;
            }
        }
        let mut b = [0.0; 18];
        for i in 0..3 {
            for c in 0..3 {
                b[6 * i + c] = area / 3.0 * e3[c];
            }
        }
        TriShell { k_unit, m, b, area, normal: e3 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mat() -> ShellMaterial {
        ShellMaterial { h: 60e-6, nu: 0.485, rho: 1100.0 }
    }

    fn quad_form<const N: usize>(k: &[[f64; N]; N], q: &[f64; N]) -> f64 {
        (0..N).map(|i| (0..N).map(|j| q[i] * k[i][j] * q[j]).sum::<f64>()).sum()
    }

    /// A skewed triangle in 3-D, counter-clockwise seen from its normal's side.
    fn nodes() -> [V3; 3] {
        [[0.1e-3, 0.2e-3, 0.3e-3], [0.55e-3, 0.25e-3, 0.1e-3], [0.2e-3, 0.6e-3, 0.45e-3]]
    }

    #[test]
    fn tri_shell_is_symmetric_and_rigid_body_motions_cost_nothing() {
        let p = nodes();
        let el = TriShell::new(p, &mat());
        let scale = (0..18).map(|i| el.k_unit[i][i].abs()).fold(0.0, f64::max);
        for i in 0..18 {
            for j in 0..18 {
                assert!((el.k_unit[i][j] - el.k_unit[j][i]).abs() <= 1e-12 * scale);
                assert_eq!(el.m[i][j], el.m[j][i]);
            }
        }
        // Three translations and three rotations about the centroid.
        for mode in 0..6 {
            let mut q = [0.0; 18];
            for (n, pn) in p.iter().enumerate() {
                if mode < 3 {
                    q[6 * n + mode] = 1.0;
                } else {
                    let mut w = [0.0; 3];
                    w[mode - 3] = 1.0;
                    let u = cross(w, *pn);
                    q[6 * n..6 * n + 3].copy_from_slice(&u);
                    q[6 * n + 3..6 * n + 6].copy_from_slice(&w);
                }
            }
            let ku: Vec<f64> = (0..18).map(|i| (0..18).map(|j| el.k_unit[i][j] * q[j]).sum()).collect();
            let worst = ku.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            assert!(worst < 1e-9 * scale * 1e-3, "rigid mode {mode}: K·q up to {worst:e} (scale {scale:e})");
        }
        // A rigid translation along the normal sweeps area × displacement.
        let mut q = [0.0; 18];
        for n in 0..3 {
            q[6 * n..6 * n + 3].copy_from_slice(&el.normal);
        }
        let vol: f64 = (0..18).map(|i| el.b[i] * q[i]).sum();
        assert!((vol / el.area - 1.0).abs() < 1e-12);
        // Total mass of each translation component is ρhA.
        let mt: f64 = (0..3).flat_map(|i| (0..3).map(move |j| (i, j))).map(|(i, j)| el.m[6 * i][6 * j]).sum();
        assert!((mt / (1100.0 * 60e-6 * el.area) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn tri_shell_dkt_passes_the_constant_curvature_patch_test() {
        // w = ½a x² + b xy + ½c y² has κ = (a, c, 2b) everywhere; DKT reproduces any
        // quadratic w exactly, so its energy must be ½ κᵀ D κ · A.
        let xy = [(0.0, 0.0), (0.7e-3, 0.1e-3), (0.2e-3, 0.5e-3)];
        let (h, nu) = (60e-6, 0.3);
        let k = dkt_bending(xy, h, nu);
        let area = 0.5 * (0.7e-3 * 0.5e-3 - 0.2e-3 * 0.1e-3);
        let d = h.powi(3) / (12.0 * (1.0 - nu * nu));
        for (a, bxy, c) in [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (0.3, -0.7, 1.1)] {
            let mut q = [0.0; 9];
            for (n, &(x, y)) in xy.iter().enumerate() {
                let (wx, wy) = (a * x + bxy * y, bxy * x + c * y);
                q[3 * n] = 0.5 * a * x * x + bxy * x * y + 0.5 * c * y * y;
                q[3 * n + 1] = wy; // θx = w,y
                q[3 * n + 2] = -wx; // θy = −w,x
            }
            let kap = [a, c, 2.0 * bxy];
            let exact = d
                * area
                * (kap[0] * kap[0] + kap[1] * kap[1] + 2.0 * nu * kap[0] * kap[1] + 0.5 * (1.0 - nu) * kap[2] * kap[2]);
            let got = quad_form(&k, &q);
            assert!((got / exact - 1.0).abs() < 1e-10, "κ = {kap:?}: {got:e} vs {exact:e}");
        }
        // The same for the membrane: u = εx·x + γ/2·y, v = εy·y + γ/2·x.
        let km = cst_membrane(xy, h, nu);
        let (ex, ey, g) = (1e-3, -4e-4, 7e-4);
        let mut q = [0.0; 6];
        for (n, &(x, y)) in xy.iter().enumerate() {
            q[2 * n] = ex * x + 0.5 * g * y;
            q[2 * n + 1] = ey * y + 0.5 * g * x;
        }
        let exact = h * area / (1.0 - nu * nu) * (ex * ex + ey * ey + 2.0 * nu * ex * ey + 0.5 * (1.0 - nu) * g * g);
        let got = quad_form(&km, &q);
        assert!((got / exact - 1.0).abs() < 1e-10, "{got:e} vs {exact:e}");
    }
}
