//! pyo3 bindings: the private `edgepose._core` module. Thin by design: it
//! checks shapes, borrows numpy buffers without copying, releases the GIL
//! for the Rust work, and raises edgepose's own exceptions
//! (`edgepose.errors`): `InvalidCloudError` for observed clouds,
//! `InvalidModelError` for object models, `ValueError` for the internal
//! arrays (codes, rotations) only the package passes. The public, typed API
//! is the Python package around it.
//!
//! - [`arrays`]: numpy ↔ Rust conversions;
//! - [`model`]: `StandardModel`, wrapped once and passed to `compute_maps`
//!   and `ModelIndex`;
//! - [`index`]: `ModelIndex` (verification, scoring, ICP) and its typed
//!   `IcpResults`;
//! - [`functions`]: the free functions (viewpoints, maps, search, segmentation).
//!
//! Every entry point runs inside [`guarded`]: a Rust panic (a bug, never an
//! input error) unwinds to there and is raised as
//! `edgepose.errors.InternalError`, an `EdgePoseError`, instead of pyo3's
//! `PanicException` (a `BaseException` that `except Exception` misses). This
//! needs `panic = "unwind"`, Rust's default, which the workspace profiles keep.

mod arrays;
mod confidence;
mod functions;
mod index;
mod model;

use std::panic::{catch_unwind, AssertUnwindSafe};

use pyo3::prelude::*;

pyo3::import_exception!(edgepose.errors, InternalError);
pyo3::import_exception!(edgepose.errors, InvalidCloudError);
pyo3::import_exception!(edgepose.errors, InvalidModelError);

/// Runs a binding's body; a panic anywhere in it (with the GIL released or
/// in a rayon worker too: both unwind back to this thread) becomes an
/// `InternalError` carrying the panic message.
fn guarded<T>(body: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    catch_unwind(AssertUnwindSafe(body)).unwrap_or_else(|payload| {
        let message = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown panic payload".into());
        Err(InternalError::new_err(format!(
            "edgepose core bug (Rust panic): {message}"
        )))
    })
}

/// Sets whether the core's parallel loops and handed-over searches started
/// from the calling thread run on it alone, and returns the previous
/// setting: `True` for a thread that shares a frame's objects with one
/// thread per core (`edgepose.workers.each`), where handing work to the
/// core's own threads only makes the threads wait on one another. The
/// results are the same either way.
#[pyfunction]
fn keep_work_on_this_thread(keep: bool) -> bool {
    crate::threads::keep_on_this_thread(keep)
}

/// TEST HOOK, not API, built only with the `test-hooks` feature (`make
/// build`, which the tests use; never the wheel): panics on purpose so the
/// tests can check that a Rust panic reaches Python as `InternalError`.
/// `where_` is "attached" (GIL held), "detached" (GIL released) or "rayon"
/// (in a worker thread).
#[cfg(feature = "test-hooks")]
#[pyfunction]
fn _panic_for_tests(py: Python<'_>, message: String, where_: &str) -> PyResult<()> {
    use rayon::prelude::*;
    guarded(|| match where_ {
        "attached" => panic!("{message}"),
        "detached" => py.detach(|| -> PyResult<()> { panic!("{message}") }),
        "rayon" => {
            py.detach(|| {
                crate::threads::install(|| {
                    (0..64)
                        .into_par_iter()
                        .for_each(|i| assert!(i < 63, "{message}"))
                })
            });
            Ok(())
        }
        _ => Err(pyo3::exceptions::PyValueError::new_err(format!(
            "unknown place {where_:?}"
        ))),
    })
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<model::PyStandardModel>()?;
    m.add_class::<index::PyModelIndex>()?;
    m.add_class::<index::PyIcpResults>()?;
    m.add_class::<index::PyScoreResults>()?;
    m.add_class::<index::PyFlipSettings>()?;
    m.add_class::<index::PyPickRules>()?;
    m.add_class::<index::PyFlipMarginSearch>()?;
    m.add_class::<index::PyDepthGrid>()?;
    m.add_class::<index::PyTrackFrameSettings>()?;
    m.add_class::<index::PyTrackedFit>()?;
    m.add_class::<confidence::PyConfidenceCurves>()?;
    m.add_function(wrap_pyfunction!(model::compute_maps, m)?)?;
    m.add_function(wrap_pyfunction!(keep_work_on_this_thread, m)?)?;
    functions::register(m)?;
    #[cfg(feature = "test-hooks")]
    m.add_function(wrap_pyfunction!(_panic_for_tests, m)?)?;
    Ok(())
}
