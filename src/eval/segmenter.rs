//! Accuracy of a segmenter against real label maps: the confusion matrix over the class table
//! (pixels whose real label is void are ignored), pixel accuracy, per-class IoU and mean IoU
//! over the classes present in the real labels (the CamVid protocol of SegNet).

use crate::classes::{ClassTable, VOID};
use crate::error::Result;
use crate::input::LabelMap;
use serde::Serialize;

/// Pixel counts of (real class, predicted class); predictions of void count as wrong.
#[derive(Debug, Clone)]
pub struct Confusion {
    classes: usize,
    /// classes x (classes + 1): the last column counts void predictions.
    counts: Vec<u64>,
}

impl Confusion {
    /// An empty matrix over `classes` classes.
    pub fn new(classes: usize) -> Self {
        Confusion { classes, counts: vec![0; classes * (classes + 1)] }
    }
    /// Adds one image (`real` and `predicted` of the same size).
    pub fn add(&mut self, real: &LabelMap, predicted: &LabelMap) -> Result<()> {
        if (real.width(), real.height()) != (predicted.width(), predicted.height()) {
            return Err(crate::Error::invalid("segmenter accuracy", "real and predicted label maps differ in size"));
        }
        for (&r, &p) in real.classes().iter().zip(predicted.classes()) {
            if r == VOID || r as usize >= self.classes {
                continue;
            }
            let col = if p == VOID || p as usize >= self.classes { self.classes } else { p as usize };
            self.counts[r as usize * (self.classes + 1) + col] += 1;
        }
        Ok(())
    }
    fn at(&self, r: usize, p: usize) -> u64 {
        self.counts[r * (self.classes + 1) + p]
    }
    /// The accuracy the counts so far give, classes named by `table`.
    pub fn report(&self, table: &ClassTable) -> SegmenterAccuracy {
        let n = self.classes;
        let total: u64 = self.counts.iter().sum();
        let correct: u64 = (0..n).map(|c| self.at(c, c)).sum();
        let mut per_class = Vec::new();
        for c in 0..n {
            let real: u64 = (0..=n).map(|p| self.at(c, p)).sum();
            if real == 0 {
                continue;
            }
            let predicted: u64 = (0..n).map(|r| self.at(r, c)).sum();
            let tp = self.at(c, c);
            per_class.push((table.name(c as u8).to_string(), tp as f64 / (real + predicted - tp) as f64));
        }
        let miou = per_class.iter().map(|x| x.1).sum::<f64>() / per_class.len().max(1) as f64;
        SegmenterAccuracy { pixels: total, pixel_accuracy: correct as f64 / total.max(1) as f64, mean_iou: miou, iou: per_class }
    }
}

/// Accuracy of a segmenter over the images compared.
#[derive(Debug, Clone, Serialize)]
pub struct SegmenterAccuracy {
    /// Labelled pixels compared.
    pub pixels: u64,
    /// Fraction of labelled pixels predicted right, in [0, 1].
    pub pixel_accuracy: f64,
    /// Mean of the per-class IoU over classes present in the real labels.
    pub mean_iou: f64,
    /// (class name, IoU) of each class present in the real labels.
    pub iou: Vec<(String, f64)>,
}

impl SegmenterAccuracy {
    /// The accuracy as text: pixel accuracy and mean IoU, then one IoU line per class, in percent.
    pub fn to_table(&self) -> String {
        let mut s = format!(
            "pixel accuracy {:.1} %, mean IoU {:.1} % ({} labelled pixels)\n",
            100.0 * self.pixel_accuracy,
            100.0 * self.mean_iou,
            self.pixels
        );
        for (name, v) in &self.iou {
            s += &format!("  {name:<14} IoU {:.1} %\n", 100.0 * v);
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accuracy_and_iou_by_hand() {
        let t = ClassTable::cityscapes();
        // real: 0 0 2 2 | void ; predicted: 0 2 2 2 | 0
        let real = LabelMap::new(5, 1, vec![0, 0, 2, 2, VOID], &t).unwrap();
        let pred = LabelMap::new(5, 1, vec![0, 2, 2, 2, 0], &t).unwrap();
        let mut c = Confusion::new(t.len());
        c.add(&real, &pred).unwrap();
        let r = c.report(&t);
        assert_eq!(r.pixels, 4);
        assert!((r.pixel_accuracy - 0.75).abs() < 1e-12);
        // road: tp 1, real 2, predicted 1 -> 1/2; building: tp 2, real 2, predicted 3 -> 2/3
        assert_eq!(r.iou.len(), 2);
        assert!((r.iou[0].1 - 0.5).abs() < 1e-12 && (r.iou[1].1 - 2.0 / 3.0).abs() < 1e-12);
        assert!((r.mean_iou - (0.5 + 2.0 / 3.0) / 2.0).abs() < 1e-12);
    }
}
