//! The confidence's calibrated model, evaluated: logistic regression over
//! each piece of evidence turned into a few terms, each term a
//! piecewise-linear curve (the term plus max(0, term − knot) at its knots).
//! The terms, their names and the fit are Python's
//! (`edgepose.confidence`); this is the per-pose sum, in the same order.

/// How a piece of evidence becomes a term (`edgepose.confidence.TERMS`).
/// A NaN stays NaN through each, as in Python's `min`/`max`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Transform {
    /// The evidence as it is.
    Value,
    /// log of the share of points left unexplained, floored at 1 %.
    Unexplained,
    /// log of a share, floored at 1 %.
    LogShare,
    /// A margin clipped to −0.2 … 0.3.
    ClippedMargin,
    /// 1 when the margin is 1 (no rival), else 0.
    NoRival,
    /// An extent up to 1.2 diameters.
    CappedExtent,
}

/// Python's `max(a, b)`: `a` unless `b > a` (so a NaN `a` stays).
fn py_max(a: f64, b: f64) -> f64 {
    if b > a {
        b
    } else {
        a
    }
}

/// Python's `min(a, b)`: `a` unless `b < a`.
fn py_min(a: f64, b: f64) -> f64 {
    if b < a {
        b
    } else {
        a
    }
}

impl Transform {
    /// The transform named as in the model's manifest (`feature:name`).
    pub fn named(name: &str) -> Option<Self> {
        Some(match name {
            "value" => Self::Value,
            "unexplained" => Self::Unexplained,
            "log_share" => Self::LogShare,
            "clipped_margin" => Self::ClippedMargin,
            "no_rival" => Self::NoRival,
            "capped_extent" => Self::CappedExtent,
            _ => return None,
        })
    }

    pub fn apply(self, v: f64) -> f64 {
        match self {
            Self::Value => v,
            Self::Unexplained => (py_max(1.0 - v, 0.0) + 0.01).ln(),
            Self::LogShare => (v + 0.01).ln(),
            Self::ClippedMargin => py_min(py_max(v, -0.2), 0.3),
            Self::NoRival => f64::from(u8::from(v >= 0.99)),
            Self::CappedExtent => py_min(v, 1.2),
        }
    }
}

/// One term of the model: a transform of one piece of evidence, its
/// weight, and its hinges `(knot, weight)`, on unstandardised terms.
#[derive(Clone, Debug, PartialEq)]
pub struct Term {
    /// Index of the evidence it reads.
    pub evidence: usize,
    pub transform: Transform,
    pub weight: f64,
    pub hinges: Vec<(f64, f64)>,
}

/// The fitted model: its terms and intercept.
#[derive(Clone, Debug, PartialEq)]
pub struct Curves {
    pub terms: Vec<Term>,
    pub intercept: f64,
}

impl Curves {
    /// P(correct | `evidence`), 0–1 (NaN when a term is); `evidence` in
    /// the order the terms index.
    pub fn probability(&self, evidence: &[f64]) -> f64 {
        let mut z = self.intercept;
        for term in &self.terms {
            let x = term.transform.apply(evidence[term.evidence]);
            let mut bent = 0.0;
            for &(knot, weight) in &term.hinges {
                if x > knot {
                    bent += weight * (x - knot);
                }
            }
            z += term.weight * x + bent;
        }
        1.0 / (1.0 + (-py_min(py_max(z, -50.0), 50.0)).exp())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_curve_bends_at_its_knots() {
        let curves = Curves {
            terms: vec![Term {
                evidence: 1,
                transform: Transform::Value,
                weight: 2.0,
                hinges: vec![(0.5, -2.0)],
            }],
            intercept: -1.0,
        };
        let p = |x: f64| curves.probability(&[f64::NAN, x]);
        // z = -1 + 2x below the knot, flat (z = 0) above it.
        assert!((p(0.0) - 1.0 / (1.0 + 1f64.exp())).abs() < 1e-15);
        assert_eq!(p(0.5), 0.5);
        assert_eq!(p(0.9), 0.5);
        assert!(p(f64::NAN).is_nan());
    }

    #[test]
    fn transforms_as_python_has_them() {
        assert_eq!(Transform::named("log_share"), Some(Transform::LogShare));
        assert_eq!(Transform::named("softplus"), None);
        assert_eq!(Transform::Unexplained.apply(1.5), 0.01f64.ln());
        assert_eq!(Transform::ClippedMargin.apply(-1.0), -0.2);
        assert_eq!(Transform::ClippedMargin.apply(1.0), 0.3);
        assert!(Transform::ClippedMargin.apply(f64::NAN).is_nan());
        assert_eq!(Transform::NoRival.apply(1.0), 1.0);
        assert_eq!(Transform::NoRival.apply(f64::NAN), 0.0);
        assert_eq!(Transform::CappedExtent.apply(3.0), 1.2);
    }
}
