//! `ConfidenceCurves`: the confidence model's per-pose sum
//! (`crate::confidence`), built once per model by `edgepose.confidence`.

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use super::guarded;
use crate::confidence::{Curves, Term, Transform};

/// A term as Python gives it: (evidence index, transform name, weight,
/// hinges (knot, weight)).
type TermArguments = (usize, String, f64, Vec<(f64, f64)>);

/// The fitted confidence model on unstandardised terms: each term
/// `(evidence index, transform name, weight, [(knot, weight), ...])`, and
/// the intercept. Immutable.
#[pyclass(frozen, name = "ConfidenceCurves", module = "edgepose._core")]
pub struct PyConfidenceCurves {
    inner: Curves,
    evidence: usize,
}

#[pymethods]
impl PyConfidenceCurves {
    #[new]
    fn new(terms: Vec<TermArguments>, intercept: f64, evidence: usize) -> PyResult<Self> {
        guarded(|| {
            let terms = terms
                .into_iter()
                .map(|(index, name, weight, hinges)| {
                    let transform = Transform::named(&name).ok_or_else(|| {
                        PyValueError::new_err(format!("unknown confidence term transform {name:?}"))
                    })?;
                    if index >= evidence {
                        return Err(PyValueError::new_err(format!(
                            "a term reads evidence {index} of {evidence}"
                        )));
                    }
                    Ok(Term {
                        evidence: index,
                        transform,
                        weight,
                        hinges,
                    })
                })
                .collect::<PyResult<Vec<_>>>()?;
            Ok(Self {
                inner: Curves { terms, intercept },
                evidence,
            })
        })
    }

    /// P(correct | `evidence`), 0–1: the model's evidence values in order.
    fn probability(&self, evidence: Vec<f64>) -> PyResult<f64> {
        if evidence.len() != self.evidence {
            return Err(PyValueError::new_err(format!(
                "{} evidence values for a model of {}",
                evidence.len(),
                self.evidence
            )));
        }
        Ok(self.inner.probability(&evidence))
    }
}
