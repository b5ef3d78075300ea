//! The worker threads of the core's parallel loops: one rayon pool per
//! process; and the threads that keep their loops to themselves
//! ([`keep_on_this_thread`]).
//!
//! Not rayon's global pool: a process forked after using it (Python's
//! `multiprocessing` on Linux, a robot stack's worker processes) inherits
//! the pool's bookkeeping but none of its threads, and its first parallel
//! loop would wait forever for them. [`pool`] forgets a pool in a forked
//! child (a `pthread_atfork` handler) or one another process started (its
//! id differs), and starts one of its own there.

use std::cell::Cell;
use std::panic::{catch_unwind, resume_unwind, AssertUnwindSafe};
use std::ptr;
use std::sync::atomic::{AtomicBool, AtomicPtr, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};

use rayon::prelude::*;
use rayon::{ThreadPool, ThreadPoolBuilder};

/// A pool and the process that started it.
struct ProcessPool {
    pid: u32,
    pool: ThreadPool,
}

static POOL: AtomicPtr<ProcessPool> = AtomicPtr::new(ptr::null_mut());

/// Whether [`forget_in_child`] is registered to run in forked children.
static FORK_HANDLER: AtomicBool = AtomicBool::new(false);

/// Runs in a forked child, right after the fork: the parent's pool (its
/// threads are not in the child) is forgotten, never dropped. Only an
/// atomic store: safe in a child of a multi-threaded process.
#[cfg(unix)]
extern "C" fn forget_in_child() {
    POOL.store(ptr::null_mut(), Ordering::Release);
}

#[cfg(unix)]
extern "C" {
    fn pthread_atfork(
        prepare: Option<extern "C" fn()>,
        parent: Option<extern "C" fn()>,
        child: Option<extern "C" fn()>,
    ) -> std::ffi::c_int;
}

/// Registers [`forget_in_child`] once, before the first pool is published.
/// The process id check in [`pool`] stays as a second guard (a child made
/// by a raw `clone`, which runs no handlers); this one also covers a
/// child whose id happens to be a finished parent's.
fn register_fork_handler() {
    #[cfg(unix)]
    if !FORK_HANDLER.swap(true, Ordering::AcqRel) {
        // SAFETY: registers a plain function with no captured state; a
        // non-zero return (out of memory) only leaves the id check.
        unsafe {
            pthread_atfork(None, None, Some(forget_in_child));
        }
    }
}

/// This process's pool, started on first use (as many threads as rayon's
/// global pool would have: `RAYON_NUM_THREADS`, else the cores this process
/// may use).
pub fn pool() -> &'static ThreadPool {
    let pid = std::process::id();
    register_fork_handler();
    loop {
        let current = POOL.load(Ordering::Acquire);
        // SAFETY: a published pool is never freed (below), so the pointer
        // stays valid for the life of the process.
        if let Some(found) = unsafe { current.as_ref() } {
            if found.pid == pid {
                return &found.pool;
            }
        }
        let fresh = Box::into_raw(Box::new(ProcessPool {
            pid,
            pool: ThreadPoolBuilder::new()
                .thread_name(|i| format!("edgepose-core-{i}"))
                .build()
                .expect("cannot start the core's worker threads"),
        }));
        match POOL.compare_exchange(current, fresh, Ordering::AcqRel, Ordering::Acquire) {
            // The pool replaced (if any) is a parent process's: its threads
            // are not in this one, so it is left as it is, never dropped.
            Ok(_) => {
                // SAFETY: just published, never freed.
                return unsafe { &(*fresh).pool };
            }
            Err(_) => {
                // Another thread published one first: use that (next turn).
                // SAFETY: `fresh` was never published; its threads are ours.
                drop(unsafe { Box::from_raw(fresh) });
            }
        }
    }
}

/// Runs `op` in this process's pool, so that its parallel loops use the
/// pool's threads (the caller waits); in the pool the caller works for
/// when it already is a pool's worker.
pub fn install<R: Send>(op: impl FnOnce() -> R + Send) -> R {
    if rayon::current_thread_index().is_some() {
        op()
    } else {
        pool().install(op)
    }
}

thread_local! {
    /// Whether this thread keeps its work to itself: see [`keep_on_this_thread`].
    static ON_THIS_THREAD: Cell<bool> = const { Cell::new(false) };
}

/// Sets whether the parallel loops ([`map`]) and handed-over jobs
/// ([`hand_over`], [`on_two_cores`]) started from this thread run on it
/// alone; returns the previous setting. For a thread that shares a
/// caller's jobs with as many threads as there are cores (the objects of
/// `estimate_many`): the cores are busy already, and handing work to the
/// pool would only make the threads wait on one another. The results are
/// the same either way.
pub fn keep_on_this_thread(keep: bool) -> bool {
    ON_THIS_THREAD.replace(keep)
}

/// Whether this thread keeps its work to itself ([`keep_on_this_thread`]).
pub fn on_this_thread() -> bool {
    ON_THIS_THREAD.get()
}

/// `f` of each of `items`, in order: in parallel in the pool (at least
/// `min_len` items a job), or on this thread when it keeps its work to
/// itself ([`keep_on_this_thread`]).
pub fn map<I: Sync, T: Send>(
    items: &[I],
    min_len: usize,
    f: impl Fn(&I) -> T + Sync + Send,
) -> Vec<T> {
    if on_this_thread() {
        items.iter().map(f).collect()
    } else {
        install(|| items.par_iter().with_min_len(min_len).map(f).collect())
    }
}

/// A job [`hand_over`] gave one of the pool's threads, and its result.
/// The caller asks for the result with [`Handed::take`]: it waits while a
/// worker runs the job, and runs the job itself when no worker has started
/// it yet, so a worker slow to wake (an idle virtual CPU can take a
/// millisecond) never holds the caller up longer than the job would.
/// Dropped unasked, a job no worker has started never runs.
pub struct Handed<T> {
    slot: Arc<(Mutex<Slot<T>>, Condvar)>,
}

type Job<T> = Box<dyn FnOnce() -> T + Send>;

enum Slot<T> {
    /// Not started (or dropped unasked: `None`).
    Waiting(Option<Job<T>>),
    /// A worker runs it.
    Running,
    /// Its result, or its panic.
    Done(std::thread::Result<T>),
}

/// `job` on one of this process's pool's threads, starting now, while the
/// caller goes on; its result comes from [`Handed::take`]. With a pool of
/// one thread, from a pool's own thread (whose pool may be busy with the
/// caller's own loops) or from one that keeps its work to itself
/// ([`keep_on_this_thread`]), no worker is asked: `take` runs it.
pub fn hand_over<T: Send + 'static>(job: impl FnOnce() -> T + Send + 'static) -> Handed<T> {
    let handed = later(job);
    let pool = pool();
    if rayon::current_thread_index().is_none()
        && pool.current_num_threads() >= 2
        && !on_this_thread()
    {
        let slot = Arc::clone(&handed.slot);
        pool.spawn(move || {
            let (lock, done) = &*slot;
            let job = {
                let mut slot = locked(lock);
                match std::mem::replace(&mut *slot, Slot::Running) {
                    Slot::Waiting(Some(job)) => job,
                    // Taken back by the caller, or dropped unasked.
                    other => {
                        *slot = other;
                        return;
                    }
                }
            };
            let result = catch_unwind(AssertUnwindSafe(job));
            *locked(lock) = Slot::Done(result);
            done.notify_all();
        });
    }
    handed
}

/// `f` of each of `items`, in order, on the caller's thread and one of the
/// pool's ([`hand_over`]): each takes the next item not yet taken, so the
/// caller never waits for a thread slow to wake longer than the item that
/// thread took (none when it never started). Each item's result is its
/// own, so the results are those of a plain loop.
pub fn on_two_cores<I, T, F>(items: Vec<I>, f: F) -> Vec<T>
where
    I: Send + Sync + 'static,
    T: Send + 'static,
    F: Fn(&I) -> T + Send + Sync + 'static,
{
    let shared = Arc::new(SharedLoop {
        items,
        next: AtomicUsize::new(0),
        f,
    });
    let theirs = {
        let shared = Arc::clone(&shared);
        hand_over(move || shared.take_each())
    };
    let mut results: Vec<Option<T>> = Vec::with_capacity(shared.items.len());
    results.resize_with(shared.items.len(), || None);
    for (i, result) in shared.take_each().into_iter().chain(theirs.take()) {
        results[i] = Some(result);
    }
    results
        .into_iter()
        .map(|r| r.expect("every item is taken once"))
        .collect()
}

/// The items of [`on_two_cores`], the next one not yet taken, and what is
/// done to each.
struct SharedLoop<I, F> {
    items: Vec<I>,
    next: AtomicUsize,
    f: F,
}

impl<I, F> SharedLoop<I, F> {
    /// Takes items until none is left: `(index, result)` of each taken.
    fn take_each<T>(&self) -> Vec<(usize, T)>
    where
        F: Fn(&I) -> T,
    {
        let mut done = Vec::new();
        loop {
            let i = self.next.fetch_add(1, Ordering::Relaxed);
            let Some(item) = self.items.get(i) else {
                return done;
            };
            done.push((i, (self.f)(item)));
        }
    }
}

/// `job`, run by the thread that asks for its result ([`Handed::take`]),
/// when it does: no worker is asked.
pub fn later<T: Send + 'static>(job: impl FnOnce() -> T + Send + 'static) -> Handed<T> {
    Handed {
        slot: Arc::new((
            Mutex::new(Slot::Waiting(Some(Box::new(job)))),
            Condvar::new(),
        )),
    }
}

/// The slot's lock; a panic never happens while it is held, so it is never poisoned.
fn locked<T>(lock: &Mutex<T>) -> MutexGuard<'_, T> {
    lock.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl<T> Handed<T> {
    /// The job's result: waited for while a worker runs it; the job run in
    /// this thread when no worker has started it. A panic in the job
    /// reaches the caller here.
    pub fn take(self) -> T {
        let (lock, done) = &*self.slot;
        let mut slot = locked(lock);
        loop {
            match std::mem::replace(&mut *slot, Slot::Running) {
                Slot::Waiting(job) => {
                    drop(slot);
                    return job.expect("only a drop leaves no job")();
                }
                Slot::Running => slot = done.wait(slot).unwrap_or_else(|p| p.into_inner()),
                Slot::Done(result) => return result.unwrap_or_else(|panic| resume_unwind(panic)),
            }
        }
    }
}

impl<T> Drop for Handed<T> {
    /// A job no worker has started is dropped with its inputs: it never runs.
    fn drop(&mut self) {
        if let Slot::Waiting(job) = &mut *locked(&self.slot.0) {
            job.take();
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn loops_run_on_the_process_pool() {
        let names: Vec<String> = install(|| {
            (0..64)
                .into_par_iter()
                .map(|_| std::thread::current().name().unwrap_or("").to_string())
                .collect()
        });
        assert!(
            names.iter().all(|n| n.starts_with("edgepose-core-")),
            "{names:?}"
        );
        assert!(std::ptr::eq(pool(), pool()));
    }

    #[test]
    fn a_thread_that_keeps_its_work_runs_its_loops_and_handed_jobs_itself() {
        let here = std::thread::current().id();
        let threads = |items: &[u64]| {
            map(items, 1, |_| {
                std::thread::sleep(std::time::Duration::from_micros(20));
                std::thread::current().id()
            })
        };
        let items: Vec<u64> = (0..64).collect();
        assert!(!on_this_thread());
        assert!(threads(&items).iter().all(|&id| id != here));
        assert!(!keep_on_this_thread(true));
        assert!(threads(&items).iter().all(|&id| id == here));
        let handed = hand_over(|| std::thread::current().id());
        std::thread::sleep(std::time::Duration::from_millis(5));
        assert_eq!(handed.take(), here);
        assert_eq!(
            on_two_cores(vec![1, 2, 3], |_| std::thread::current().id()),
            [here; 3]
        );
        assert!(keep_on_this_thread(false));
        assert_eq!(
            map(&items, 4, |i| i * i),
            items.iter().map(|i| i * i).collect::<Vec<_>>()
        );
    }

    #[test]
    fn two_cores_give_each_items_result_in_order() {
        for count in [0, 1, 2, 7, 100] {
            let items: Vec<u64> = (0..count).collect();
            let squares = on_two_cores(items, |i| {
                // Uneven work, so the two threads take items out of step.
                std::thread::sleep(std::time::Duration::from_micros(i % 3 * 50));
                i * i
            });
            assert_eq!(squares, (0..count).map(|i| i * i).collect::<Vec<_>>());
        }
        // With every worker held, the caller takes every item itself.
        let release = hold_the_workers();
        assert_eq!(on_two_cores(vec![1, 2, 3], |i| i + 1), [2, 3, 4]);
        drop(release);
    }

    /// Holds every worker of the process's pool until the returned sender
    /// is dropped (or sent to); returns once all of them are held.
    pub(crate) fn hold_the_workers() -> std::sync::mpsc::Sender<()> {
        let (release, held) = std::sync::mpsc::channel::<()>();
        let held = Arc::new(Mutex::new(held));
        let (started, wait_started) = std::sync::mpsc::channel();
        for _ in 0..pool().current_num_threads() {
            let (held, started) = (Arc::clone(&held), started.clone());
            pool().spawn(move || {
                started.send(()).unwrap();
                let _ = held.lock().unwrap().recv();
            });
        }
        for _ in 0..pool().current_num_threads() {
            wait_started.recv().unwrap();
        }
        release
    }

    // The tests that hold the pool's workers (below, and `refine`'s) take
    // this lock: they run one at a time.
    pub(crate) static HOLDING: Mutex<()> = Mutex::new(());

    #[test]
    fn a_handed_job_no_worker_started_is_run_by_the_caller() {
        let _one_at_a_time = HOLDING.lock().unwrap_or_else(|p| p.into_inner());
        let name = || std::thread::current().name().unwrap_or("").to_string();
        let release = hold_the_workers();
        let runs = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let counted = Arc::clone(&runs);
        let handed = hand_over(move || {
            counted.fetch_add(1, Ordering::SeqCst);
            name()
        });
        assert_eq!(
            handed.take(),
            name(),
            "taken back while every worker was busy"
        );
        // A job dropped unasked is never run, even once a worker is free.
        let ran = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&ran);
        drop(hand_over(move || flag.store(true, Ordering::SeqCst)));
        drop(release);
        install(|| ()); // the workers are free again ...
        std::thread::sleep(std::time::Duration::from_millis(50)); // ... and any job left has run
        assert!(!ran.load(Ordering::SeqCst));
        assert_eq!(
            runs.load(Ordering::SeqCst),
            1,
            "the job taken back ran once"
        );
    }

    #[test]
    fn a_handed_job_runs_on_a_worker_and_its_result_or_panic_comes_back() {
        let _one_at_a_time = HOLDING.lock().unwrap_or_else(|p| p.into_inner());
        let (started, wait_started) = std::sync::mpsc::channel();
        let handed = hand_over(move || {
            started.send(()).unwrap();
            // Asked for while a worker runs it: waited for.
            std::thread::sleep(std::time::Duration::from_millis(30));
            std::thread::current().name().unwrap_or("").to_string()
        });
        if pool().current_num_threads() > 1 {
            wait_started.recv().unwrap();
            let on = handed.take();
            assert!(on.starts_with("edgepose-core-"), "{on}");
        } else {
            assert_eq!(handed.take(), std::thread::current().name().unwrap_or(""));
        }
        // A panic reaches the caller, whoever ran the job.
        let handed = hand_over(|| -> u8 { panic!("the job's own panic") });
        let panicked = std::panic::catch_unwind(AssertUnwindSafe(|| handed.take()));
        assert!(panicked.is_err());
        assert_eq!(later(|| 8).take(), 8);
    }

    #[test]
    fn inside_another_pool_its_threads_are_used() {
        let other = ThreadPoolBuilder::new()
            .num_threads(3)
            .thread_name(|i| format!("other-{i}"))
            .build()
            .unwrap();
        let name = other.install(|| install(|| std::thread::current().name().unwrap().to_string()));
        assert!(name.starts_with("other-"), "{name}");
    }
}
