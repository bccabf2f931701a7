//! A parallel map that reports progress on the caller's thread.

use rayon::prelude::*;

/// `f` of every item of `items`, in parallel on a scoped thread and collected in their order,
/// while the caller's thread calls `done(k)` as the `k`-th of them (from 1) ends: a reporter
/// that cannot leave the caller's thread still sees every item end.
pub fn map_reporting<T: Sync, R: Send>(
    items: &[T],
    f: impl Fn(&T) -> R + Sync + Send,
    mut done: impl FnMut(usize),
) -> Vec<R> {
    let (tx, rx) = std::sync::mpsc::channel::<()>();
    std::thread::scope(|s| {
        let work = s.spawn(move || {
            items
                .par_iter()
                .map(|x| {
                    let r = f(x);
                    // The receiver outlives the senders; a failed send only loses a report.
                    let _ = tx.send(());
                    r
                })
                .collect()
        });
        for (k, ()) in rx.iter().enumerate() {
            done(k + 1);
        }
        work.join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_keep_their_order_and_every_item_is_reported() {
        // Oracle: the sequential map, and one report per item counting 1..=n.
        let items: Vec<u64> = (0..50).collect();
        let mut seen = Vec::new();
        let out = map_reporting(&items, |x| x * x, |k| seen.push(k));
        assert_eq!(out, items.iter().map(|x| x * x).collect::<Vec<_>>());
        assert_eq!(seen, (1..=50).collect::<Vec<_>>());
    }
}
