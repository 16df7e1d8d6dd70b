//! VPR-Bench metrics (Zaffar et al., IJCV 2021, `performance_comparison.py`; `docs/design/method.md` §4.3).
//!
//! Each query contributes its top-1 score s(q) and whether its top-1 reference is correct y(q).
//! The precision-recall curve is scikit-learn's `precision_recall_curve(y, s)`: one point per
//! distinct score threshold, recall = TP / (number of correct top-1 queries), plus the final
//! (recall 0, precision 1) point.
//! - AUC: trapezoidal area under that curve (`sklearn.metrics.auc(recall, precision)`);
//! - Recall@100%Precision: 0 if the most confident threshold already has a wrong query, else the
//!   recall of the lowest threshold whose precision is 1;
//! - Precision@100%Recall: the best precision among points with recall 1.
//!
//! One deliberate deviation: when no query is correct at all, recall is undefined; scikit-learn
//! then sets it to 1 and reports an AUC of 0.5. We report 0 for all three.

use serde::Serialize;

/// Points of the precision-recall curve, ordered as scikit-learn returns them: by increasing
/// threshold, then the appended (precision 1, recall 0). `scores` and `correct` are parallel
/// (one entry per query); slices of different lengths panic, as `copy_from_slice` does.
pub fn precision_recall_curve(scores: &[f64], correct: &[bool]) -> (Vec<f64>, Vec<f64>) {
    assert_eq!(scores.len(), correct.len());
    let mut order: Vec<usize> = (0..scores.len()).collect();
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]));
    let (mut tps, mut fps) = (Vec::new(), Vec::new());
    let (mut tp, mut fp) = (0.0, 0.0);
    for (k, &i) in order.iter().enumerate() {
        if correct[i] {
            tp += 1.0;
        } else {
            fp += 1.0;
        }
        let last_of_threshold = k + 1 == order.len() || scores[order[k + 1]] != scores[i];
        if last_of_threshold {
            tps.push(tp);
            fps.push(fp);
        }
    }
    let total_tp = tp;
    let mut precision: Vec<f64> = tps.iter().zip(&fps).map(|(t, f)| t / (t + f)).rev().collect();
    let mut recall: Vec<f64> = tps.iter().map(|t| if total_tp > 0.0 { t / total_tp } else { 1.0 }).rev().collect();
    precision.push(1.0);
    recall.push(0.0);
    (precision, recall)
}

/// Trapezoidal area under (recall, precision); recall is monotone, decreasing as returned.
pub fn auc(recall: &[f64], precision: &[f64]) -> f64 {
    let area: f64 = recall.windows(2).zip(precision.windows(2)).map(|(r, p)| (r[1] - r[0]) * (p[0] + p[1]) / 2.0).sum();
    area.abs()
}

/// AUC, R@100P and P@100R of one query set.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PrMetrics {
    /// Area under the precision-recall curve, in [0, 1].
    pub auc: f64,
    /// Recall at 100 % precision, in [0, 1].
    pub recall_at_100_precision: f64,
    /// Precision at 100 % recall, in [0, 1].
    pub precision_at_100_recall: f64,
}

/// The metrics of one query set from its top-1 `scores` and whether each top-1 is `correct`
/// (parallel slices); all 0 when no query is correct.
pub fn pr_metrics(scores: &[f64], correct: &[bool]) -> PrMetrics {
    if !correct.iter().any(|&c| c) {
        return PrMetrics { auc: 0.0, recall_at_100_precision: 0.0, precision_at_100_recall: 0.0 };
    }
    let (p, r) = precision_recall_curve(scores, correct);
    let r100p = if p[p.len() - 2] < 1.0 {
        0.0
    } else {
        // the curve ends with the appended precision-1 point
        let first = p.iter().position(|&v| v == 1.0).unwrap_or(p.len() - 1);
        r[first]
    };
    let p100r = p.iter().zip(&r).filter(|(_, &rr)| rr == 1.0).map(|(&pp, _)| pp).fold(0.0, f64::max);
    PrMetrics { auc: auc(&r, &p), recall_at_100_precision: r100p, precision_at_100_recall: p100r }
}

/// Fraction of queries with a correct reference among their first `n` ranked references.
/// `ranked` and `ground_truth` are parallel (one entry per query); slices of different lengths
/// panic, as `copy_from_slice` does.
pub fn recall_at_n(ranked: &[Vec<u32>], ground_truth: &[Vec<u32>], n: usize) -> f64 {
    assert_eq!(ranked.len(), ground_truth.len());
    if ranked.is_empty() {
        return 0.0;
    }
    let hits = ranked.iter().zip(ground_truth).filter(|(r, gt)| r.iter().take(n).any(|x| gt.contains(x))).count();
    hits as f64 / ranked.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m(scores: &[f64], correct: &[bool]) -> (f64, f64, f64) {
        let r = pr_metrics(scores, correct);
        (r.auc, r.recall_at_100_precision, r.precision_at_100_recall)
    }

    #[test]
    fn all_correct_gives_ones() {
        assert_eq!(m(&[0.9, 0.5, 0.7, 0.1], &[true; 4]), (1.0, 1.0, 1.0));
    }

    #[test]
    fn most_confident_wrong_gives_zero_recall_at_full_precision() {
        let (_, r100p, _) = m(&[0.9, 0.8, 0.7, 0.6], &[false, true, true, true]);
        assert_eq!(r100p, 0.0);
    }

    #[test]
    fn low_scoring_correct_query_lowers_precision_at_full_recall() {
        // sorted: .9 T, .8 T, .7 F, .6 F, .5 T  -> recall 1 first reached at 5 accepted, 3 correct
        let (auc, r100p, p100r) = m(&[0.9, 0.8, 0.7, 0.6, 0.5], &[true, true, false, false, true]);
        assert!((p100r - 3.0 / 5.0).abs() < 1e-12);
        assert!((r100p - 2.0 / 3.0).abs() < 1e-12);
        // sklearn: precision [0.6, 0.5, 0.667, 1, 1, 1], recall [1, .667, .667, .667, .333, 0]
        let expected = (1.0 - 2.0 / 3.0) * (0.6 + 0.5) / 2.0 + (2.0 / 3.0 - 1.0 / 3.0) * 1.0 + (1.0 / 3.0) * 1.0;
        assert!((auc - expected).abs() < 1e-12, "{auc} vs {expected}");
    }

    #[test]
    fn curve_matches_sklearn_with_ties() {
        // y = [1, 0, 1, 1], s = [0.8, 0.8, 0.5, 0.2]  (sklearn 1.5 output)
        let (p, r) = precision_recall_curve(&[0.8, 0.8, 0.5, 0.2], &[true, false, true, true]);
        assert_eq!(p, vec![0.75, 2.0 / 3.0, 0.5, 1.0]);
        assert_eq!(r, vec![1.0, 2.0 / 3.0, 1.0 / 3.0, 0.0]);
        assert_eq!(m(&[0.8, 0.8, 0.5, 0.2], &[true, false, true, true]).1, 0.0);
    }

    #[test]
    fn nothing_correct_is_all_zero_and_recall_at_n_counts_hits() {
        assert_eq!(m(&[0.3, 0.2], &[false, false]), (0.0, 0.0, 0.0));
        let ranked = vec![vec![3, 1], vec![0, 2], vec![5, 6]];
        let gt = vec![vec![1], vec![0], vec![9]];
        assert!((recall_at_n(&ranked, &gt, 1) - 1.0 / 3.0).abs() < 1e-12);
        assert!((recall_at_n(&ranked, &gt, 2) - 2.0 / 3.0).abs() < 1e-12);
    }
}
