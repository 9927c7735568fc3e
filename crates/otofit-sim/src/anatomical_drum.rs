//! An anatomical finite-element eardrum (`DrumShape::Anatomical`, `--drum anatomical`):
//! the whole pars tensa on an elliptical outline, a conical shape, a measured thickness
//! distribution, the manubrium as a rigid strip of finite width attached along its
//! length, and a compliant fibrous annulus at the rim instead of a clamp. Built from the
//! flat-shell triangles of [`super::tri_shell`] and condensed onto the malleus exactly
//! through its modes ([`ManubriumModes`]), as the manubrium drum is.
//!
//! Every constant below carries its source; none was chosen to fit a norm.
//!
//! Geometry. The ring mesh of [`super::drum_mesh::ring_mesh`] on the unit disc, (ξ, η) =
//! (ρ cos φ, ρ sin φ), mapped onto an ellipse of semi-axes `radius_x` (anterior–posterior)
//! and `radius_y` (along the manubrium, superior = +y); the umbo is the apex at the centre
//! and the drum is the elliptical cone z = depth·(1 − ρ_e), ρ_e = √((x/a_x)² + (y/a_y)²),
//! z medial. Only the half x ≥ 0 is meshed: outline, cone, strip and annulus are symmetric
//! about x = 0 and so are the loads (w_umbo, θ_m, the pressures), so antisymmetric motions
//! do not reach the boundary and the condensed answer is the whole drum's (every element
//! counted twice, u_x = θ_y = θ_z = 0 on the plane; `drum_mesh.rs` tests the same
//! reduction against the full mesh).
//!
//! Manubrium. The plane nodes from the umbo to the lateral process are moved sideways to
//! x = b(y), the strip's half-width, and the unmeshed region 0 ≤ x ≤ b(y) between them and
//! the plane is the rigid manubrium strip: its nodes and its area move as the malleus
//! does, u_z = w_umbo − y·θ_m, θ_x = −θ_m (a rotation about an axis parallel to x, the
//! convention of `model.rs`), u_x = u_y = θ_y = θ_z = 0. The strip is clamped to the
//! membrane along its edges (no hinge), and the in-plane part of the rotation,
//! u_y = θ_m·(z − z_axis), is neglected as in the manubrium drum. Interior nodes between
//! the strip and the rim are moved by b(y)·(1 − ξ/ξ_rim) so that no element inverts. The
//! strip's width tapers to zero over [`MANUBRIUM_TAPER`] at both ends, so its outline does
//! not depend on the mesh.
//!
//! Annulus. At each rim node a strip of annulus tissue of square cross-section (side c,
//! the annulus' caliber, varying around the rim as measured) reaches from the membrane's
//! edge to the bone, where it is clamped: a Timoshenko cantilever per unit rim length in
//! transverse bending and shear on (u_z, the slope σ = −θ·t along the outward normal m),
//! plus radial stretch E·t/((1 − ν²)L) along m and shear G·t/L along the tangent t, each
//! multiplied by the node's share of the rim length. Above the malleus neck the annulus is
//! absent (the notch of Rivinus): there the membrane meets bone and is pinned
//! (translations held, rotations free; Gea et al. 2010 JARO 11:1 found the human pars
//! flaccida's edge neither clamped nor free). The annulus' own mass is left out (massless
//! springs).
//!
//! Moduli. E_eardrum scales the whole drum, the annulus included, through the published
//! ratio of the annulus' modulus to the pars tensa's ([`ANNULUS_MODULUS_RATIO`]), so the
//! drum's stiffness is E_eardrum·K_unit and its modes are computed once per mesh. Loss:
//! the drum's complex modulus as `model.rs` forms it (the anatomical ear uses a
//! frequency-independent loss factor, [`LOSS_FACTOR`], not Rayleigh damping).
//!
//! Solvers. [`DrumSolver::Modes`] (default): the generalized eigenvectors of the half
//! drum, once per mesh and process ([`AnatomicalDrum::condensed_shared`]), then a few
//! sums per frequency. [`DrumSolver::Direct`]: the same condensed block by a sparse
//! complex LU of the interior at every frequency, for meshes too large for a dense
//! eigendecomposition (the mesh-convergence reference) and as an independent check of
//! the modes.

use super::drum::{DrumCoefficients, DrumError};
use super::drum_mesh::{Dof, DrumFe, FREE, ManubriumModes, PAIRS, number_dofs, ring_mesh};
use super::tri_shell::{ShellMaterial, TriShell};
use faer::linalg::solvers::Solve;
use faer::sparse::{SparseColMat, Triplet};
use faer::{Mat, c64};
use std::f64::consts::PI;
use std::sync::{Arc, Mutex};

/// Semi-axis of the outline across the manubrium (anterior–posterior), m: half the
/// horizontal diameter 8.0 ± 1.1 mm of cadaver morphometry (Talas et al. 2021, Diving
/// Hyperb Med 51:10; physics-notes §1.2).
pub const RADIUS_X: f64 = 4.0e-3;
/// Semi-axis along the manubrium (inferior–superior), m: half the vertical diameter
/// 9.5 ± 1.3 mm (Talas et al. 2021). With [`RADIUS_X`] the pars tensa's projected area is
/// π·4.0·4.75 = 59.7 mm² (the 60 mm² of impedance models, Hudde & Engel 1998; notes §1.2).
pub const RADIUS_Y: f64 = 4.75e-3;
/// Cone depth of the umbo below the annulus plane, m (2.0 mm, range 1.5–2.5: a cone
/// half-angle of 65–70°; notes §1.2).
pub const DEPTH: f64 = 2.0e-3;
/// Manubrium length from the umbo to the lateral process along the drum, m (4.41 mm in
/// micro-CT; range 4–5.5 mm; notes §1.2). The lateral process lies where this length,
/// measured along the cone, ends.
pub const MANUBRIUM_LENGTH: f64 = 4.4e-3;
/// Width of the membrane's attachment to the manubrium, m: the malleus handle is about
/// 0.5–1 mm wide along its length (micro-CT of the human middle ear, De Greef et al. 2015
/// J Morphol 276:1025, read as an order of magnitude [L]); the middle of that range.
pub const MANUBRIUM_WIDTH: f64 = 0.7e-3;
/// Length over which the strip's width tapers to zero at each end, m (the spatulate umbo
/// end and the lateral process; a shape choice of the order of the width [L], so that the
/// strip's outline does not depend on the mesh).
pub const MANUBRIUM_TAPER: f64 = 0.3e-3;
/// Pars tensa thickness in the middle of the membrane, m: thinnest between annulus and
/// umbo, about 50–90 µm (Kuypers et al. 2006, Otol Neurotol 27:256, confocal microscopy of
/// fresh human drums, overall range 40–120 µm; posterosuperior mean about 69 µm against
/// 85 µm elsewhere, notes §1.2).
pub const THICKNESS_MIDDLE: f64 = 70e-6;
/// Thickness at the rim, m: the membrane thickens toward the annulus (Kuypers et al. 2006;
/// Van der Jeught et al. 2013, JARO 14:483, OCT of fresh drums), to about 100 µm, inside
/// the 40–120 µm range.
pub const THICKNESS_RIM: f64 = 100e-6;
/// Thickness at the umbo, m: the membrane also thickens toward the umbo (Van der Jeught et
/// al. 2013), to about 90 µm.
pub const THICKNESS_UMBO: f64 = 90e-6;
/// Fraction of the normalised radius over which the thickness rises to [`THICKNESS_RIM`]
/// (outer 20 %) and falls from [`THICKNESS_UMBO`] (inner 20 %): the thickened bands of
/// Kuypers et al. 2006 and Van der Jeught et al. 2013 span about 1 mm of a 4–5 mm radius.
pub const THICKENED_BAND: f64 = 0.2;
/// Soft-tissue density, kg/m³ (notes §0: 1100, Motallebzadeh 2017).
pub const DENSITY: f64 = 1100.0;
/// Poisson ratio of the membrane (notes §0: 0.3–0.49 for soft tissue, the study's 0.485).
pub const POISSON: f64 = 0.485;
/// Annulus modulus over pars tensa modulus: 0.6 MPa against 35 MPa in Gan, Feng & Sun
/// 2004 (Ann Biomed Eng 32:847; the same 0.6 MPa in Koike et al. 2002, JASA 111:1306;
/// tabulated with a 32 MPa pars tensa in Hindawi Appl Bionics Biomech 2018:1736957,
/// table 1). At the nominal E_eardrum of 20 MPa the annulus is 0.34 MPa.
pub const ANNULUS_MODULUS_RATIO: f64 = 0.6 / 35.0;
/// Annulus Poisson ratio (0.3 in Gan et al. 2004's table).
pub const ANNULUS_POISSON: f64 = 0.3;
/// Largest annulus caliber, m, inferiorly opposite the manubrium: 748 ± 201 µm (Kassem et
/// al. 2010, Otolaryngol Head Neck Surg 142:394, 23 human drums).
pub const ANNULUS_CALIBER_MAX: f64 = 748e-6;
/// Smallest annulus caliber, m, at its ends beside the notch: about 15 % of the largest,
/// 113 ± 42 and 152 ± 87 µm (Kassem et al. 2010).
pub const ANNULUS_CALIBER_MIN: f64 = 130e-6;
/// Half-angle of the notch of Rivinus seen from the umbo, rad: the annulus is a horseshoe
/// "absent above the neck of the malleus" (Kassem et al. 2010); the notch spans about
/// 40° of the rim in otoscopic anatomy [L].
pub const NOTCH_HALF_ANGLE: f64 = 20.0 * PI / 180.0;
/// The anatomical ear's drum loss factor η (E·(1 + jη), frequency-independent): the
/// human drum's loss tangent is 0.1–0.3 over the audio band (Zhang & Gan 2011; the
/// dynamic tests of Daphalapurkar et al. 2009; notes §2 and §4); the middle of that
/// range.
pub const LOSS_FACTOR: f64 = 0.2;
/// The default mesh density: rings from the umbo to the rim. Against 40 rings at the
/// softest prior modulus (1 MPa) the 8 kHz features move by at most 0.13 test–retest
/// STDs at 20 rings and 0.22 at 16 (`tests/fe_drum.rs`, `measure_mesh_convergence`;
/// docs/results/fe-drum.md).
pub const RINGS: usize = 20;

/// How the rim is held.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Annulus {
    /// The fibrous annulus as springs to the bone (module docs), pinned at the notch.
    Springs,
    /// Every rim node clamped (the limit of an infinitely stiff annulus).
    Clamped,
}

/// How the condensed block is computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DrumSolver {
    /// Through the drum's modes (once per mesh): the fast path.
    Modes,
    /// By a sparse LU of the interior at every frequency (large meshes, checks).
    Direct,
}

/// The anatomical drum's shape, materials and mesh. [`Default`] is the cited values.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AnatomicalDrum {
    /// Rings of triangles from the umbo to the rim.
    pub rings: usize,
    /// Semi-axis across the manubrium, m.
    pub radius_x: f64,
    /// Semi-axis along the manubrium, m.
    pub radius_y: f64,
    /// Cone depth, m.
    pub depth: f64,
    /// Manubrium length along the drum, m (0: only the umbo node is attached).
    pub manubrium_length: f64,
    /// Width of the manubrium strip, m (0: a line).
    pub manubrium_width: f64,
    /// Taper length of the strip's ends, m.
    pub manubrium_taper: f64,
    /// Thickness in the middle, at the rim and at the umbo, m.
    pub thickness: [f64; 3],
    /// Density, kg/m³.
    pub density: f64,
    /// Poisson ratio.
    pub poisson: f64,
    /// How the rim is held.
    pub annulus: Annulus,
    /// Annulus modulus over the pars tensa's.
    pub annulus_ratio: f64,
    /// Annulus caliber at its ends and inferiorly, m.
    pub annulus_caliber: [f64; 2],
    /// Half-angle of the pinned notch, rad.
    pub notch_half_angle: f64,
    /// Modes or direct solve.
    pub solver: DrumSolver,
}

impl Default for AnatomicalDrum {
    fn default() -> Self {
        AnatomicalDrum {
            rings: RINGS,
            radius_x: RADIUS_X,
            radius_y: RADIUS_Y,
            depth: DEPTH,
            manubrium_length: MANUBRIUM_LENGTH,
            manubrium_width: MANUBRIUM_WIDTH,
            manubrium_taper: MANUBRIUM_TAPER,
            thickness: [THICKNESS_MIDDLE, THICKNESS_RIM, THICKNESS_UMBO],
            density: DENSITY,
            poisson: POISSON,
            annulus: Annulus::Springs,
            annulus_ratio: ANNULUS_MODULUS_RATIO,
            annulus_caliber: [ANNULUS_CALIBER_MIN, ANNULUS_CALIBER_MAX],
            notch_half_angle: NOTCH_HALF_ANGLE,
            solver: DrumSolver::Modes,
        }
    }
}

/// How a node of the half mesh is held.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum NodeKind {
    /// Free (on the symmetry plane or not).
    Free,
    /// On the manubrium strip's edge, `s` (m) from the umbo along y.
    Manubrium {
        /// In-plane distance from the umbo along y, m.
        s: f64,
    },
    /// On the rim, held by the annulus; `psi` is its angle from the superior (+y) axis,
    /// rad, and `share` its share of the rim length in the half mesh, m.
    Rim {
        /// Angle from +y seen from the umbo, rad.
        psi: f64,
        /// Rim length the node carries, m.
        share: f64,
    },
    /// On the rim at the notch: pinned.
    Notch,
    /// On the rim, clamped.
    Clamped,
}

/// The half mesh (x ≥ 0) on the drum's surface.
#[derive(Clone, Debug)]
pub struct HalfMesh {
    /// Node coordinates, m.
    pub nodes: Vec<[f64; 3]>,
    /// Counter-clockwise triangles (normals toward +z).
    pub tris: Vec<[usize; 3]>,
    /// How each node is held.
    pub kind: Vec<NodeKind>,
    /// Whether each node lies on the symmetry plane x = 0.
    pub on_plane: Vec<bool>,
    /// The strip's edge from the umbo to the lateral process: (b, y) per manubrium node.
    pub strip: Vec<(f64, f64)>,
}

impl AnatomicalDrum {
    /// The lateral process' in-plane distance from the umbo along y, m: the manubrium's
    /// length measured along the cone's generator.
    pub fn manubrium_reach(&self) -> f64 {
        self.manubrium_length / (1.0 + (self.depth / self.radius_y).powi(2)).sqrt()
    }

    /// The strip's half-width at distance y from the umbo, m.
    fn half_width(&self, y: f64) -> f64 {
        let l = self.manubrium_reach();
        if !(0.0..=l).contains(&y) || self.manubrium_width == 0.0 {
            return 0.0;
        }
        let taper = if self.manubrium_taper > 0.0 { (y.min(l - y) / self.manubrium_taper).min(1.0) } else { 1.0 };
        0.5 * self.manubrium_width * taper.max(0.0)
    }

    /// Thickness at normalised radius ρ, m.
    fn thickness_at(&self, rho: f64) -> f64 {
        let [mid, rim, umbo] = self.thickness;
        let band = THICKENED_BAND;
        if rho >= 1.0 - band {
            mid + (rim - mid) * (rho - (1.0 - band)) / band
        } else if rho <= band {
            umbo + (mid - umbo) * rho / band
        } else {
            mid
        }
    }

    /// The half mesh: nodes mapped onto the ellipse, the cone and around the strip.
    pub fn mesh(&self) -> HalfMesh {
        assert!(self.rings >= 1, "at least one ring");
        let (polar, tris) = ring_mesh(self.rings);
        let tol = 1e-12;
        let l_man = self.manubrium_reach();
        let (ax, ay) = (self.radius_x, self.radius_y);
        let mut index = vec![usize::MAX; polar.len()];
        let mut mesh = HalfMesh { nodes: vec![], tris: vec![], kind: vec![], on_plane: vec![], strip: vec![] };
        for (i, &(rho, phi)) in polar.iter().enumerate() {
            let (xi, eta) = (rho * phi.cos(), rho * phi.sin());
            if xi < -tol {
                continue;
            }
            index[i] = mesh.nodes.len();
            let plane = xi.abs() <= tol;
            let rim = rho >= 1.0 - tol;
            let y = eta * ay;
            let xi_rim = (1.0 - eta * eta).max(0.0).sqrt();
            let shift = if rim || xi_rim == 0.0 { 0.0 } else { self.half_width(y) * (1.0 - xi.max(0.0) / xi_rim) };
            let x = if plane { 0.0 } else { xi * ax } + shift;
            let rho_e = ((x / ax).powi(2) + (y / ay).powi(2)).sqrt().min(1.0);
            mesh.nodes.push([x, y, self.depth * (1.0 - rho_e)]);
            mesh.on_plane.push(plane && shift == 0.0);
            let kind = if rim {
                let psi = eta.clamp(-1.0, 1.0).acos();
                match self.annulus {
                    Annulus::Clamped => NodeKind::Clamped,
                    Annulus::Springs if psi < self.notch_half_angle => NodeKind::Notch,
                    Annulus::Springs => NodeKind::Rim { psi, share: 0.0 },
                }
            } else if plane && (0.0..=l_man * (1.0 + 1e-9)).contains(&y) {
                mesh.strip.push((shift, y));
                NodeKind::Manubrium { s: y }
            } else {
                NodeKind::Free
            };
            mesh.kind.push(kind);
        }
        for t in &tris {
            if t.iter().all(|&v| index[v] != usize::MAX) {
                let tri = t.map(|v| index[v]);
                let p = tri.map(|v| mesh.nodes[v]);
                let two_a = (p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[2][0] - p[0][0]) * (p[1][1] - p[0][1]);
                assert!(two_a > 0.0, "the strip's shift inverted triangle {tri:?}: {p:?}");
                mesh.tris.push(tri);
            }
        }
        // Each rim node carries half of each rim edge it ends (an edge between two rim
        // nodes belongs to one triangle).
        for t in mesh.tris.clone() {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                let on_rim = |v: usize| !matches!(mesh.kind[v], NodeKind::Free | NodeKind::Manubrium { .. });
                if on_rim(a) && on_rim(b) {
                    let d = sub(mesh.nodes[a], mesh.nodes[b]);
                    let half = 0.5 * dot(d, d).sqrt();
                    for v in [a, b] {
                        if let NodeKind::Rim { share, .. } = &mut mesh.kind[v] {
                            *share += half;
                        }
                    }
                }
            }
        }
        mesh
    }

    /// The drum's matrices for E_eardrum = 1 Pa over its interior and the two malleus
    /// DOFs: shell triangles, annulus springs and the rigid strip's own area and mass.
    pub fn fe(&self) -> DrumFe {
        let mesh = self.mesh();
        let place = |node: usize, c: usize| -> Option<[f64; 2]> {
            match mesh.kind[node] {
                NodeKind::Clamped => None,
                NodeKind::Notch if c < 3 => None,
                NodeKind::Manubrium { s } => match c {
                    2 => Some([1.0, -s]),
                    3 => Some([0.0, -1.0]),
                    _ => None,
                },
                _ if mesh.on_plane[node] && matches!(c, 0 | 4 | 5) => None,
                _ => FREE,
            }
        };
        let (dofs, n) = number_dofs(mesh.nodes.len(), place);
        let mut fe = DrumFe::empty(n);
        // Every element of the half counts twice (module docs).
        for t in &mesh.tris {
            let p = t.map(|v| mesh.nodes[v]);
            let rho = (0..3)
                .map(|k| ((p[k][0] / self.radius_x).powi(2) + (p[k][1] / self.radius_y).powi(2)).sqrt())
                .sum::<f64>()
                / 3.0;
            let mat = ShellMaterial { h: self.thickness_at(rho.min(1.0)), nu: self.poisson, rho: self.density };
            let el = TriShell::new(p, &mat);
            fe.add_element(&el, |i| dofs[6 * t[i / 6] + i % 6], 2.0);
        }
        self.add_annulus(&mesh, &dofs, &mut fe);
        self.add_strip(&mesh, &mut fe);
        fe.dofs = dofs;
        fe
    }

    /// The annulus' springs, per unit pars tensa modulus (module docs).
    fn add_annulus(&self, mesh: &HalfMesh, dofs: &[Dof], fe: &mut DrumFe) {
        let (e, nu) = (self.annulus_ratio, ANNULUS_POISSON);
        let g = e / (2.0 * (1.0 + nu));
        let [c_min, c_max] = self.annulus_caliber;
        for (node, kind) in mesh.kind.iter().enumerate() {
            let NodeKind::Rim { psi, share } = *kind else { continue };
            let span = PI - self.notch_half_angle;
            let c = c_min + (c_max - c_min) * ((psi - self.notch_half_angle) / span).clamp(0.0, 1.0);
            let k = AnnulusStrip::new(e, g, nu, c);
            let [x, y, _] = mesh.nodes[node];
            let m = unit([x / self.radius_x.powi(2), y / self.radius_y.powi(2), 0.0]);
            let t = [-m[1], m[0], 0.0];
            // Per node DOF vectors: u_z; σ = −θ·t; u·m; u·t. Weight 2: the half model.
            let w = [0.0, 0.0, 1.0, 0.0, 0.0, 0.0];
            let sigma = [0.0, 0.0, 0.0, -t[0], -t[1], 0.0];
            let radial = [m[0], m[1], 0.0, 0.0, 0.0, 0.0];
            let tangential = [t[0], t[1], 0.0, 0.0, 0.0, 0.0];
            let scale = 2.0 * share;
            let mut add = |a: &[f64; 6], b: &[f64; 6], kv: f64| {
                for i in 0..6 {
                    for j in 0..6 {
                        let v = scale * kv * a[i] * b[j];
                        if let (Dof::Free(gi), Dof::Free(gj)) = (dofs[6 * node + i], dofs[6 * node + j])
                            && v != 0.0
                        {
                            fe.k_ii.push((gi, gj, v));
                        }
                    }
                }
            };
            add(&w, &w, k.ww);
            add(&w, &sigma, k.w_sigma);
            add(&sigma, &w, k.w_sigma);
            add(&sigma, &sigma, k.sigma_sigma);
            add(&radial, &radial, k.radial);
            add(&tangential, &tangential, k.tangential);
        }
    }

    /// The rigid strip between the plane and the strip's edge: its projected area moves as
    /// u_z = w − y·θ (swept volume ∫(1, −y) dA) and its membrane mass rides on the malleus.
    fn add_strip(&self, mesh: &HalfMesh, fe: &mut DrumFe) {
        let mut pts = mesh.strip.clone();
        pts.sort_by(|a, b| a.1.total_cmp(&b.1));
        let slope = (1.0 + (self.depth / self.radius_y).powi(2)).sqrt(); // surface / projected
        let (mut a0, mut a1) = (0.0, 0.0); // ∫1 and ∫y over the half strip
        let mut mass_area = [0.0; 3];
        for w in pts.windows(2) {
            let ((b0, y0), (b1, y1)) = (w[0], w[1]);
            let dy = y1 - y0;
            // Trapezoid with linear width b(y) between the two nodes.
            let i0 = 0.5 * (b0 + b1) * dy;
            let i1 = dy * (b0 * (2.0 * y0 + y1) + b1 * (y0 + 2.0 * y1)) / 6.0;
            let i2 = dy
                * (b0 * (3.0 * y0 * y0 + 2.0 * y0 * y1 + y1 * y1) + b1 * (y0 * y0 + 2.0 * y0 * y1 + 3.0 * y1 * y1))
                / 12.0;
            a0 += i0;
            a1 += i1;
            let h = self.thickness_at(0.5 * (y0 + y1) / self.radius_y);
            let rho_h = self.density * h * slope;
            mass_area[0] += rho_h * i0;
            mass_area[1] += rho_h * i1;
            mass_area[2] += rho_h * i2;
        }
        fe.b_b[0] += 2.0 * a0;
        fe.b_b[1] -= 2.0 * a1;
        fe.m_bb[0][0] += 2.0 * mass_area[0];
        fe.m_bb[0][1] -= 2.0 * mass_area[1];
        fe.m_bb[1][0] -= 2.0 * mass_area[1];
        fe.m_bb[1][1] += 2.0 * mass_area[2];
    }

    /// The condensed drum (modes or direct, as `solver` says), computed once per process
    /// for each drum: the eigensolution takes seconds and every model of a process shares it.
    pub fn condensed_shared(&self) -> Result<Arc<AnatomicalCondensed>, DrumError> {
        static CACHE: Mutex<Vec<(String, Arc<AnatomicalCondensed>)>> = Mutex::new(Vec::new());
        let key = format!("{self:?}");
        if let Some((_, m)) = CACHE.lock().unwrap_or_else(|e| e.into_inner()).iter().find(|(k, _)| *k == key) {
            return Ok(Arc::clone(m));
        }
        let condensed = Arc::new(self.condensed()?);
        CACHE.lock().unwrap_or_else(|e| e.into_inner()).push((key, Arc::clone(&condensed)));
        Ok(condensed)
    }

    /// The condensed drum, computed now.
    pub fn condensed(&self) -> Result<AnatomicalCondensed, DrumError> {
        let fe = self.fe();
        Ok(match self.solver {
            DrumSolver::Modes => AnatomicalCondensed::Modes(super::mode_cache::modes(&fe)?),
            DrumSolver::Direct => {
                AnatomicalCondensed::Direct(Box::new(DirectDrum { own: ManubriumModes::boundary_only(&fe), fe }))
            }
        })
    }
}

/// Stiffness per unit rim length of the annulus strip (a clamped Timoshenko cantilever
/// of width L = c and thickness t = c), per unit pars tensa modulus.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AnnulusStrip {
    /// Transverse (u_z) stiffness, N/m per m.
    pub ww: f64,
    /// Transverse–slope coupling, N/m per m·m.
    pub w_sigma: f64,
    /// Slope stiffness, N·m per m.
    pub sigma_sigma: f64,
    /// Radial stretch, N/m per m.
    pub radial: f64,
    /// Tangential shear, N/m per m.
    pub tangential: f64,
}

impl AnnulusStrip {
    /// The strip of modulus `e`, shear modulus `g`, Poisson ratio `nu` and caliber `c`:
    /// Timoshenko beam element with its far end clamped (Przemieniecki 1968, Theory of
    /// Matrix Structural Analysis, §5.6): EI/((1 + φ)L³)·[[12, 6L], [6L, (4 + φ)L²]] with
    /// φ = 12EI/(κGAL²), κ = 5/6, in cylindrical bending (EI → E t³/(12(1 − ν²)) per
    /// unit length, A → t).
    pub fn new(e: f64, g: f64, nu: f64, c: f64) -> AnnulusStrip {
        let (t, l) = (c, c);
        let d = e * t.powi(3) / (12.0 * (1.0 - nu * nu));
        let phi = 12.0 * d / (5.0 / 6.0 * g * t * l * l);
        let f = d / ((1.0 + phi) * l.powi(3));
        AnnulusStrip {
            ww: 12.0 * f,
            w_sigma: 6.0 * l * f,
            sigma_sigma: (4.0 + phi) * l * l * f,
            radial: e * t / ((1.0 - nu * nu) * l),
            tangential: g * t / l,
        }
    }
}

/// The drum's interior condensed onto (w_umbo, θ_m, p_drum, p_cavity).
#[derive(Debug)]
pub enum AnatomicalCondensed {
    /// Through the modes.
    Modes(ManubriumModes),
    /// By a sparse solve per call.
    Direct(Box<DirectDrum>),
}

/// The drum kept whole: a sparse complex LU of κK + sM per frequency.
#[derive(Debug)]
pub struct DirectDrum {
    fe: DrumFe,
    own: ManubriumModes,
}

impl DirectDrum {
    /// X = (κK + sM)⁻¹·G with G = [K_ib,w, K_ib,θ, M_ib,w, M_ib,θ, b_i] (n×5).
    ///
    /// # Panics
    /// When κK + sM is singular (a lossless drum exactly at a natural frequency; with
    /// Im κ > 0 it never is).
    fn solve(&self, c: &DrumCoefficients) -> Mat<c64> {
        let fe = &self.fe;
        let mut trip: Vec<Triplet<usize, usize, c64>> = Vec::with_capacity(fe.k_ii.len() + fe.m_ii.len());
        trip.extend(fe.k_ii.iter().map(|&(i, j, v)| Triplet::new(i, j, c.kappa * v)));
        trip.extend(fe.m_ii.iter().map(|&(i, j, v)| Triplet::new(i, j, c64::new(c.s * v, 0.0))));
        let a = SparseColMat::<usize, c64>::try_new_from_triplets(fe.n, fe.n, &trip).expect("drum matrix assembles");
        let lu = a.sp_lu().expect("the drum's interior is not singular");
        let g = Mat::<c64>::from_fn(fe.n, 5, |i, j| {
            c64::new(
                match j {
                    0 | 1 => fe.k_ib[j][i],
                    2 | 3 => fe.m_ib[j - 2][i],
                    _ => fe.b_i[i],
                },
                0.0,
            )
        });
        lu.solve(g)
    }

    fn g(&self, i: usize, a: usize) -> f64 {
        match a {
            0 | 1 => self.fe.k_ib[a][i],
            2 | 3 => self.fe.m_ib[a - 2][i],
            _ => self.fe.b_i[i],
        }
    }

    fn block(&self, c: &DrumCoefficients) -> [[c64; 4]; 4] {
        let x = self.solve(c);
        let mut h = [c64::new(0.0, 0.0); 15];
        for (e, &(a, b)) in PAIRS.iter().enumerate() {
            h[e] = (0..self.fe.n).map(|i| x[(i, b)] * self.g(i, a)).sum();
        }
        self.own.finish(c, &h)
    }

    /// Interior displacements for boundary values (w, θ, p_drum, p_cavity).
    fn interior(&self, c: &DrumCoefficients, xb: [c64; 4]) -> Vec<c64> {
        let x = self.solve(c);
        let coef = [c.kappa * xb[0], c.kappa * xb[1], c.s * xb[0], c.s * xb[1], xb[3] - xb[2]];
        (0..self.fe.n).map(|i| -(0..5).map(|a| x[(i, a)] * coef[a]).sum::<c64>()).collect()
    }
}

impl AnatomicalCondensed {
    /// The drum's 4×4 block on rows (malleus force, malleus moment, flow, cavity) and
    /// columns (w_umbo, θ_m, p_drum, p_cavity), as [`ManubriumModes::block`].
    pub fn block(&self, c: &DrumCoefficients) -> [[c64; 4]; 4] {
        match self {
            AnatomicalCondensed::Modes(m) => m.block(c),
            AnatomicalCondensed::Direct(d) => d.block(c),
        }
    }

    /// The drum's swept volume and qᴴK_unit q (its loss is ½ω·Im κ times the latter) for
    /// boundary values (w, θ, p_drum, p_cavity).
    pub fn volume_and_energy(&self, c: &DrumCoefficients, xb: [c64; 4]) -> (c64, f64) {
        match self {
            AnatomicalCondensed::Modes(m) => {
                let eta = m.interior(c, xb);
                (m.volume(&eta, xb[0], xb[1]), m.unit_stiffness_energy(&eta, xb[0], xb[1]))
            }
            AnatomicalCondensed::Direct(d) => {
                let q = d.interior(c, xb);
                let fe = &d.fe;
                let mut vol: c64 = q.iter().zip(&fe.b_i).map(|(qi, bi)| qi * *bi).sum();
                vol += xb[0] * fe.b_b[0] + xb[1] * fe.b_b[1];
                let mut kq = vec![c64::new(0.0, 0.0); fe.n];
                for &(i, j, v) in &fe.k_ii {
                    kq[i] += q[j] * v;
                }
                let mut e: f64 = q.iter().zip(&kq).map(|(a, b)| (a.conj() * b).re).sum();
                for (i, qi) in q.iter().enumerate() {
                    let kx = xb[0] * fe.k_ib[0][i] + xb[1] * fe.k_ib[1][i];
                    e += 2.0 * (qi.conj() * kx).re;
                }
                for i in 0..2 {
                    for j in 0..2 {
                        e += (xb[i].conj() * xb[j]).re * fe.k_bb[i][j];
                    }
                }
                (vol, e)
            }
        }
    }

    /// Natural frequencies (Hz) with the manubrium held at modulus `e` (modes only).
    pub fn frequencies(&self, e: f64) -> Option<Vec<f64>> {
        match self {
            AnatomicalCondensed::Modes(m) => Some(m.frequencies(e)),
            AnatomicalCondensed::Direct(_) => None,
        }
    }
}

type V3 = [f64; 3];

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn unit(a: V3) -> V3 {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat circular plate of radius `a` and uniform thickness `h`, only its centre node
    /// on the malleus, the rim as `annulus` all round (no notch).
    fn plate(a: f64, h: f64, rings: usize, annulus: Annulus, ratio: f64, caliber: f64) -> AnatomicalDrum {
        AnatomicalDrum {
            rings,
            radius_x: a,
            radius_y: a,
            depth: 0.0,
            manubrium_length: 0.0,
            manubrium_width: 0.0,
            thickness: [h; 3],
            poisson: 0.3,
            annulus,
            annulus_ratio: ratio,
            annulus_caliber: [caliber; 2],
            notch_half_angle: 0.0,
            ..AnatomicalDrum::default()
        }
    }

    /// Static volume and centre deflection per unit pressure at modulus `e`, the malleus
    /// DOFs (w, θ) free and unloaded: the condensed block's mechanics rows at ω = 0.
    fn static_response(drum: &AnatomicalDrum, e: f64) -> (f64, f64) {
        let cond = drum.condensed().unwrap();
        let c = DrumCoefficients { kappa: c64::new(e, 0.0), s: 0.0, jw: c64::new(0.0, 0.0), cavity: 0.0 };
        let bl = cond.block(&c);
        // [b00 b01; b10 b11](w, θ) = −(b02, b12)·p with p = 1.
        let det = bl[0][0] * bl[1][1] - bl[0][1] * bl[1][0];
        let w = (-bl[0][2] * bl[1][1] + bl[1][2] * bl[0][1]) / det;
        let t = (-bl[1][2] * bl[0][0] + bl[0][2] * bl[1][0]) / det;
        let (vol, _) = cond.volume_and_energy(&c, [w, t, c64::new(1.0, 0.0), c64::new(0.0, 0.0)]);
        (vol.re, w.re)
    }

    /// Volume per unit pressure of an axisymmetric Kirchhoff plate on an elastic edge
    /// (per unit length: [[k_ww, k_wσ], [k_wσ, k_σσ]] on (w(a), w′(a))), written from the
    /// plate equation: w = q r⁴/(64D) + C₁r² + C₂, with C₁, C₂ from stationary total
    /// potential energy (exact Gauss quadrature of the polynomial integrands).
    fn elastic_edge_plate_volume(a: f64, d: f64, nu: f64, k: [f64; 3]) -> f64 {
        let q = 1.0;
        // Gauss–Legendre, 4 points on [0, a]: exact to degree 7.
        let (xg, wg) = (
            [-0.861_136_311_594_052_6, -0.339_981_043_584_856_3, 0.339_981_043_584_856_3, 0.861_136_311_594_052_6],
            [0.347_854_845_137_453_9, 0.652_145_154_862_546_1, 0.652_145_154_862_546_1, 0.347_854_845_137_453_9],
        );
        let quad = |f: &dyn Fn(f64) -> f64| -> f64 {
            (0..4).map(|i| wg[i] * f(0.5 * a * (xg[i] + 1.0))).sum::<f64>() * 0.5 * a
        };
        // Shapes (value, first, second derivative): particular, r², 1.
        let shape = |k: usize, r: f64| -> [f64; 3] {
            match k {
                0 => [q * r.powi(4) / (64.0 * d), q * r.powi(3) / (16.0 * d), 3.0 * q * r * r / (16.0 * d)],
                1 => [r * r, 2.0 * r, 2.0],
                _ => [1.0, 0.0, 0.0],
            }
        };
        let form = |i: usize, j: usize| -> f64 {
            let plate = quad(&|r: f64| {
                let (u, v) = (shape(i, r), shape(j, r));
                let (u1, v1) = (u[1] / r, v[1] / r);
                (u[2] * v[2] + u1 * v1 + nu * (u[2] * v1 + u1 * v[2])) * r
            }) * 2.0
                * PI
                * d;
            let (ue, ve) = (shape(i, a), shape(j, a));
            let edge =
                2.0 * PI * a * (k[0] * ue[0] * ve[0] + k[1] * (ue[0] * ve[1] + ue[1] * ve[0]) + k[2] * ue[1] * ve[1]);
            plate + edge
        };
        let load = |j: usize| quad(&|r: f64| shape(j, r)[0] * r) * 2.0 * PI * q;
        // a(w_p + C₁φ₁ + C₂φ₂, φ_j) = l(φ_j), j = 1, 2.
        let m = [[form(1, 1), form(2, 1)], [form(1, 2), form(2, 2)]];
        let r = [load(1) - form(0, 1), load(2) - form(0, 2)];
        let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
        let c1 = (r[0] * m[1][1] - r[1] * m[0][1]) / det;
        let c2 = (m[0][0] * r[1] - m[1][0] * r[0]) / det;
        load(0) / q + c1 * load(1) / q + c2 * load(2) / q
    }

    #[test]
    fn the_edge_plate_formula_has_the_textbook_clamped_and_simply_supported_limits() {
        // The closed form itself, against πqa⁶/(192D) (clamped) and
        // πqa⁶(7 + ν)/(192D(1 + ν)) (simply supported).
        let (a, d, nu): (f64, f64, f64) = (4.4e-3, 1e-6, 0.3);
        let clamped = PI * a.powi(6) / (192.0 * d);
        let ss = PI * a.powi(6) * (7.0 + nu) / (192.0 * d * (1.0 + nu));
        let v = elastic_edge_plate_volume(a, d, nu, [1e12, 0.0, 1e12]);
        assert!((v / clamped - 1.0).abs() < 1e-6, "{v:e} vs {clamped:e}");
        let v = elastic_edge_plate_volume(a, d, nu, [1e12, 0.0, 0.0]);
        assert!((v / ss - 1.0).abs() < 1e-5, "{v:e} vs {ss:e}");
    }

    #[test]
    fn clamped_flat_plate_matches_the_closed_form() {
        // notes §5.3: centre w₀ = qa⁴/(64D), ΔV = πqa⁶/(192D).
        let (a, h, e, nu): (f64, f64, f64, f64) = (4.4e-3, 60e-6, 20e6, 0.3);
        let d = e * h.powi(3) / (12.0 * (1.0 - nu * nu));
        for rings in [8, 16] {
            let (vol, w0) = static_response(&plate(a, h, rings, Annulus::Clamped, 0.0, 1e-4), e);
            let (v_exact, w_exact) = (PI * a.powi(6) / (192.0 * d), a.powi(4) / (64.0 * d));
            eprintln!("rings {rings}: volume {:.4}, centre {:.4} of the closed form", vol / v_exact, w0 / w_exact);
            let tol = if rings == 16 { 0.01 } else { 0.03 };
            assert!((vol / v_exact - 1.0).abs() < tol, "rings {rings}: volume {vol:e} vs {v_exact:e}");
            assert!((w0 / w_exact - 1.0).abs() < tol, "rings {rings}: centre {w0:e} vs {w_exact:e}");
        }
    }

    #[test]
    fn annulus_springs_match_the_elastic_edge_closed_form_and_stiffen_to_the_clamp() {
        let (a, h, e, nu): (f64, f64, f64, f64) = (4.4e-3, 60e-6, 20e6, 0.3);
        let d = e * h.powi(3) / (12.0 * (1.0 - nu * nu));
        let clamped = static_response(&plate(a, h, 16, Annulus::Clamped, 0.0, 1e-4), e).0;
        // A compliant annulus (0.6 MPa, 0.2 mm caliber) and one 10⁶× stiffer.
        for (ratio, cal) in [(0.6e6 / e, 0.2e-3), (0.6e6 / e, 0.75e-3), (1e6 * 0.6e6 / e, 0.2e-3)] {
            let ea = ratio * e;
            let k = AnnulusStrip::new(ea, ea / (2.0 * (1.0 + ANNULUS_POISSON)), ANNULUS_POISSON, cal);
            let exact = elastic_edge_plate_volume(a, d, nu, [k.ww, k.w_sigma, k.sigma_sigma]);
            let (fe, _) = static_response(&plate(a, h, 16, Annulus::Springs, ratio, cal), e);
            eprintln!(
                "annulus {:.1e} Pa, caliber {cal:e}: FE {fe:.4e}, closed form {exact:.4e} ({:+.2} %), clamped {clamped:.4e}",
                ea,
                100.0 * (fe / exact - 1.0)
            );
            assert!((fe / exact - 1.0).abs() < 0.01, "FE {fe:e} vs closed form {exact:e}");
            if ratio > 1.0 {
                assert!((fe / clamped - 1.0).abs() < 0.005, "stiff annulus {fe:e} vs clamped {clamped:e}");
            } else {
                assert!(fe > 1.01 * clamped, "a compliant annulus adds compliance: {fe:e} vs {clamped:e}");
            }
        }
    }

    #[test]
    fn the_outline_is_anatomical() {
        let drum = AnatomicalDrum::default();
        let mesh = drum.mesh();
        let xs = mesh.nodes.iter().map(|p| p[0]).fold(0.0, f64::max);
        let ys = (
            mesh.nodes.iter().map(|p| p[1]).fold(f64::MIN, f64::max),
            mesh.nodes.iter().map(|p| p[1]).fold(0.0, f64::min),
        );
        assert!((2.0 * xs - 8.0e-3).abs() < 1e-9 && (ys.0 - ys.1 - 9.5e-3).abs() < 1e-9, "{xs} {ys:?}");
        // Projected area (whole drum, strip included) ≈ π·a_x·a_y = 59.7 mm² (the polygon
        // inscribed in the ellipse is a little smaller).
        let tri_area: f64 = mesh
            .tris
            .iter()
            .map(|t| {
                let p = t.map(|v| mesh.nodes[v]);
                0.5 * ((p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[2][0] - p[0][0]) * (p[1][1] - p[0][1]))
            })
            .sum();
        let strip: f64 = mesh.strip.windows(2).map(|w| (w[0].0 + w[1].0) * (w[1].1 - w[0].1)).sum();
        let area = 2.0 * tri_area + strip;
        eprintln!("strip {:.2} mm², pars tensa {:.2} mm², {} interior DOFs", strip * 1e6, area * 1e6, drum.fe().n);
        assert!(area * 1e6 > 59.0 && area * 1e6 < 59.7, "projected area {:.2} mm²", area * 1e6);
        // The strip: 0.7 mm wide over 4.06 mm, less its tapered ends: about 2.6 mm².
        assert!((strip * 1e6 - 0.7 * (drum.manubrium_reach() * 1e3 - 0.3)).abs() < 0.15, "{strip:e}");
        let depth = mesh.nodes.iter().map(|p| p[2]).fold(0.0, f64::max);
        assert!((depth - 2.0e-3).abs() < 1e-12);
    }

    #[test]
    fn the_direct_solve_gives_the_modal_block() {
        let drum = AnatomicalDrum { rings: 6, ..AnatomicalDrum::default() };
        let modes = drum.condensed().unwrap();
        let direct = AnatomicalDrum { solver: DrumSolver::Direct, ..drum }.condensed().unwrap();
        for (e, eta, f, cav) in [(20e6, 0.2, 300.0, 0.0), (1e6, 0.2, 8000.0, 3e11), (3e8, 0.1, 2500.0, 0.0)] {
            let w = 2.0 * PI * f;
            let c = DrumCoefficients { kappa: c64::new(e, e * eta), s: -w * w, jw: c64::new(0.0, w), cavity: cav };
            let (bm, bd) = (modes.block(&c), direct.block(&c));
            for i in 0..4 {
                for j in 0..4 {
                    let scale = bm[i][j].norm().max(1e-300);
                    assert!(
                        (bm[i][j] - bd[i][j]).norm() <= 1e-8 * scale,
                        "({i},{j}) {f} Hz: {} vs {}",
                        bm[i][j],
                        bd[i][j]
                    );
                }
            }
            let xb = [c64::new(1e-9, 2e-10), c64::new(-3e-8, 1e-8), c64::new(1.0, 0.2), c64::new(0.1, 0.0)];
            let ((vm, em), (vd, ed)) = (modes.volume_and_energy(&c, xb), direct.volume_and_energy(&c, xb));
            assert!((vm - vd).norm() <= 1e-8 * vm.norm() && (em - ed).abs() <= 1e-8 * em.abs(), "{vm} {vd} {em} {ed}");
        }
    }
}
