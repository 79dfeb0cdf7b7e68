//! Views named in patient terms: `anterior`, `posterior`, `left`, `right`, `superior`,
//! `inferior`, mapped through a volume's [`Placement`] (its axis directions in the DICOM
//! patient frame, LPS: +x to the patient's left, +y posterior, +z superior) to a view
//! [`Orientation`] in the volume's own axis frame.
//!
//! A named view is what an observer standing on that side of the patient sees, displayed as
//! radiologists do: `anterior` is the observer in front of the patient, head up, the patient's
//! left on the screen's right; `inferior` looks from the feet, anterior up, the patient's left
//! on the right (the usual axial display). For an observer looking along `forward` with `up`,
//! the screen's right is `forward × up`, so the screen axes (u right, v up; LPS) are:
//!
//! | view      | observer looks along | u (right) | v (up) | n = u × v |
//! |-----------|----------------------|-----------|--------|-----------|
//! | anterior  | +P (from the front)  | L (+x)    | S (+z) | A (−y)    |
//! | posterior | +A (from behind)     | R (−x)    | S      | P (+y)    |
//! | left      | +R (from the left)   | P (+y)    | S      | L (+x)    |
//! | right     | +L (from the right)  | A (−y)    | S      | R (−x)    |
//! | superior  | +I (from above)      | R (−x)    | A (−y) | S (+z)    |
//! | inferior  | +S (from the feet)   | L (+x)    | A (−y) | I (−z)    |
//!
//! The camera's n = u × v therefore points from the volume towards the observer (the image is
//! the one seen from the +n side). For an axis-aligned (identity) placement the volume frame
//! is the patient frame, and `anterior` is (α, β) = (−π/2, 0): u = (−sin α, cos α, 0) = +x,
//! v = (−cos α sin β, −sin α sin β, cos β) = +z, n = (cos α cos β, sin α cos β, sin β) = −y.
//!
//! In a mirrored (left-handed) placement n = u × v computed in the volume frame is the
//! opposite patient direction; u and v, and so the X-ray image, are still the named view's.
//!
//! The basis is expressed in the volume's orthonormal axis frame (unit steps along its x, y,
//! z axes, in mm when the camera works in physical units); with anisotropic spacing the
//! camera must scale voxel indices by the spacing for the view to be the named one.

use super::{basis_from_angles, cross, dot, Orientation};
use crate::volume::Placement;
use thiserror::Error;

/// A view named after the side of the patient it is seen from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PatientView {
    /// From the front (AP display).
    Anterior,
    /// From behind.
    Posterior,
    /// From the patient's left side.
    Left,
    /// From the patient's right side.
    Right,
    /// From above the head.
    Superior,
    /// From the feet (the usual axial display).
    Inferior,
}

/// Why a named view cannot be resolved.
#[derive(Debug, Error, PartialEq)]
#[non_exhaustive]
pub enum PatientViewError {
    /// The name is not one of the six.
    #[error(
        "unknown patient view {0:?}; choose anterior, posterior, left, right, superior or inferior"
    )]
    UnknownName(String),
    /// The volume has no placement, so patient directions are unknown.
    #[error("the volume's orientation in the patient is unknown (its source gave none); give the view as angles instead")]
    NoPlacement,
    /// The placement's directions are not orthonormal.
    #[error("the volume's placement is invalid: {0}")]
    BadPlacement(String),
}

impl PatientView {
    /// All six, in the order of their names.
    pub const ALL: [PatientView; 6] = [
        PatientView::Anterior,
        PatientView::Posterior,
        PatientView::Left,
        PatientView::Right,
        PatientView::Superior,
        PatientView::Inferior,
    ];

    /// Parses a name (case-insensitive; `a`, `p`, `l`, `r`, `s`, `i` and `front`, `back`,
    /// `top`, `feet` are accepted too).
    pub fn from_name(name: &str) -> Result<PatientView, PatientViewError> {
        Ok(match name.trim().to_ascii_lowercase().as_str() {
            "anterior" | "a" | "front" => PatientView::Anterior,
            "posterior" | "p" | "back" => PatientView::Posterior,
            "left" | "l" => PatientView::Left,
            "right" | "r" => PatientView::Right,
            "superior" | "s" | "top" => PatientView::Superior,
            "inferior" | "i" | "feet" => PatientView::Inferior,
            _ => return Err(PatientViewError::UnknownName(name.to_string())),
        })
    }

    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            PatientView::Anterior => "anterior",
            PatientView::Posterior => "posterior",
            PatientView::Left => "left",
            PatientView::Right => "right",
            PatientView::Superior => "superior",
            PatientView::Inferior => "inferior",
        }
    }

    /// Screen axes (u right, v up) in the patient frame (LPS), per the table above.
    pub fn patient_axes(self) -> ([f64; 3], [f64; 3]) {
        const L: [f64; 3] = [1.0, 0.0, 0.0];
        const R: [f64; 3] = [-1.0, 0.0, 0.0];
        const P: [f64; 3] = [0.0, 1.0, 0.0];
        const A: [f64; 3] = [0.0, -1.0, 0.0];
        const S: [f64; 3] = [0.0, 0.0, 1.0];
        match self {
            PatientView::Anterior => (L, S),
            PatientView::Posterior => (R, S),
            PatientView::Left => (P, S),
            PatientView::Right => (A, S),
            PatientView::Superior => (R, A),
            PatientView::Inferior => (L, A),
        }
    }

    /// The view orientation in the volume's axis frame: the patient axes expressed in the
    /// placement's directions (re-orthonormalised, since stored directions are orthonormal
    /// only to their precision), as an explicit basis.
    pub fn orientation(
        self,
        placement: Option<&Placement>,
    ) -> Result<Orientation, PatientViewError> {
        let p = placement.ok_or(PatientViewError::NoPlacement)?;
        p.validate()
            .map_err(|e| PatientViewError::BadPlacement(e.to_string()))?;
        let (up, vp) = self.patient_axes();
        let d = &p.directions;
        let to_volume = |x: [f64; 3]| [dot(d[0], x), dot(d[1], x), dot(d[2], x)];
        let u = normalize(to_volume(up));
        let v0 = to_volume(vp);
        let k = dot(v0, u);
        let v = normalize([v0[0] - k * u[0], v0[1] - k * u[1], v0[2] - k * u[2]]);
        Ok(Orientation::Basis { u, v })
    }
}

fn normalize(x: [f64; 3]) -> [f64; 3] {
    let n = dot(x, x).sqrt();
    [x[0] / n, x[1] / n, x[2] / n]
}

/// The spherical angles (α, β) of an orthonormal basis (u, v), when it is one (u has no z
/// component); `None` otherwise (use the basis).
pub fn angles_of(u: [f64; 3], v: [f64; 3]) -> Option<(f64, f64)> {
    if u[2].abs() > 1e-9 {
        return None;
    }
    let alpha = (0.0 - u[0]).atan2(u[1]);
    let (sa, ca) = alpha.sin_cos();
    let beta = (-(v[0] * ca + v[1] * sa)).atan2(v[2]);
    let (bu, bv) = basis_from_angles(alpha, beta);
    let close = |a: [f64; 3], b: [f64; 3]| (0..3).all(|i| (a[i] - b[i]).abs() < 1e-9);
    (close(bu, u) && close(bv, v)).then_some((alpha, beta))
}

/// The view direction n = u × v of an orientation (towards the observer; see the module
/// documentation).
pub fn normal_of(o: &Orientation) -> [f64; 3] {
    let (u, v) = match *o {
        Orientation::Angles { alpha, beta } => basis_from_angles(alpha, beta),
        Orientation::Basis { u, v } => (u, v),
    };
    cross(u, v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;

    fn basis(o: Orientation) -> ([f64; 3], [f64; 3]) {
        match o {
            Orientation::Basis { u, v } => (u, v),
            Orientation::Angles { .. } => panic!("expected a basis"),
        }
    }

    fn close(a: [f64; 3], b: [f64; 3]) -> bool {
        (0..3).all(|i| (a[i] - b[i]).abs() < 1e-9)
    }

    #[test]
    fn identity_placement_gives_the_table() {
        let id = Placement::identity();
        let expect = [
            (PatientView::Anterior, (-FRAC_PI_2, 0.0), [0.0, -1.0, 0.0]),
            (PatientView::Posterior, (FRAC_PI_2, 0.0), [0.0, 1.0, 0.0]),
            (PatientView::Left, (0.0, 0.0), [1.0, 0.0, 0.0]),
            (
                PatientView::Right,
                (std::f64::consts::PI, 0.0),
                [-1.0, 0.0, 0.0],
            ),
            (
                PatientView::Superior,
                (FRAC_PI_2, FRAC_PI_2),
                [0.0, 0.0, 1.0],
            ),
            (
                PatientView::Inferior,
                (-FRAC_PI_2, -FRAC_PI_2),
                [0.0, 0.0, -1.0],
            ),
        ];
        for (view, (a, b), n) in expect {
            let o = view.orientation(Some(&id)).unwrap();
            let (u, v) = basis(o);
            let (alpha, beta) = angles_of(u, v).unwrap();
            assert!(
                (alpha - a).abs() < 1e-9 && (beta - b).abs() < 1e-9,
                "{view:?}: {alpha} {beta}"
            );
            assert!(close(normal_of(&o), n), "{view:?}");
            // The observer looks along −n: n points towards the observer.
            assert_eq!(PatientView::from_name(view.name()).unwrap(), view);
        }
        assert!(PatientView::from_name("sideways").is_err());
        assert_eq!(PatientView::from_name("A").unwrap(), PatientView::Anterior);
    }

    #[test]
    fn rotated_and_mirrored_placements_map_back_to_the_patient_axes() {
        // A sagittal acquisition: x along P, y along I (rows go down), z = x × y along R.
        let sag = Placement {
            origin: [10.0, -20.0, 30.0],
            directions: [[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]],
        };
        // A mirrored (left-handed) frame: the screen axes still map to the patient's.
        let mirrored = Placement {
            origin: [0.0; 3],
            directions: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]],
        };
        // A RAS-stored volume (as NIfTI converts): x along R, y along A, z along S.
        let ras = Placement {
            origin: [0.0; 3],
            directions: [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        // An oblique one, orthonormal only to 6 decimals, as DICOM stores it.
        let c = 0.866025;
        let obl = Placement {
            origin: [0.0; 3],
            directions: [[c, 0.5, 0.0], [-0.5, c, 0.0], [0.0, 0.0, 1.0]],
        };
        for p in [sag, ras, obl, mirrored] {
            for view in PatientView::ALL {
                let (u, v) = basis(view.orientation(Some(&p)).unwrap());
                // Orthonormal to the precision the renderer requires.
                assert!((dot(u, u) - 1.0).abs() < 1e-12 && (dot(v, v) - 1.0).abs() < 1e-12);
                assert!(dot(u, v).abs() < 1e-12);
                // Back in the patient frame: Σ uᵢ dᵢ is the table's axis.
                let back = |x: [f64; 3]| {
                    let d = &p.directions;
                    [0, 1, 2].map(|c| x[0] * d[0][c] + x[1] * d[1][c] + x[2] * d[2][c])
                };
                let (pu, pv) = view.patient_axes();
                let tol = |a: [f64; 3], b: [f64; 3]| (0..3).all(|i| (a[i] - b[i]).abs() < 2e-6);
                assert!(tol(back(u), pu), "{view:?} {p:?}: {:?}", back(u));
                assert!(tol(back(v), pv), "{view:?} {p:?}: {:?}", back(v));
            }
        }
        // The sagittal volume seen from the left: the observer looks along R = +z, and n
        // points back towards the observer: −z.
        let o = PatientView::Left.orientation(Some(&sag)).unwrap();
        assert!(close(normal_of(&o), [0.0, 0.0, -1.0]));
        // Anterior view of the sagittal volume: screen up (S) is −y of the volume.
        let (_, v) = basis(PatientView::Anterior.orientation(Some(&sag)).unwrap());
        assert!(close(v, [0.0, -1.0, 0.0]));
    }

    #[test]
    fn unknown_or_invalid_placements_are_errors() {
        assert_eq!(
            PatientView::Anterior.orientation(None),
            Err(PatientViewError::NoPlacement)
        );
        let mut bad = Placement::identity();
        bad.directions[1] = [1.0, 0.0, 0.0];
        assert!(matches!(
            PatientView::Left.orientation(Some(&bad)),
            Err(PatientViewError::BadPlacement(_))
        ));
        // A basis with a z component in u has no angles.
        assert!(angles_of([0.0, 0.6, 0.8], [0.0, -0.8, 0.6]).is_none());
    }
}
