//! Camera poses of dataset frames: SYNTHIA's CameraParams files and the pose lists of Extended
//! CMU Seasons / RobotCar Seasons (quaternion or matrix per image), all to a camera centre and
//! optical axis in world coordinates.

use super::frames::{Pose, PoseFormat};
use crate::error::{Error, Result};
use std::path::Path;

fn parse_numbers(text: &str, path: &Path, line: usize) -> Result<Vec<f64>> {
    text.split_whitespace()
        .map(|t| {
            t.parse::<f64>().ok().filter(|v| v.is_finite()).ok_or_else(|| Error::dataset(path, format!("line {line}: {t:?} is not a finite number")))
        })
        .collect()
}

/// A SYNTHIA CameraParams file: 16 numbers, column-major 4x4 camera-to-world.
pub fn read_synthia_pose(path: &Path) -> Result<Pose> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_synthia_pose(&text, path)
}

/// [`read_synthia_pose`] on a file's text; `path` only names the source in errors.
pub fn parse_synthia_pose(text: &str, path: &Path) -> Result<Pose> {
    let v = parse_numbers(text, path, 1)?;
    if v.len() != 16 {
        return Err(Error::dataset(path, format!("expected 16 numbers, found {}", v.len())));
    }
    // column-major: column j is v[4j..4j+4]; the camera's z axis is column 2, the centre column 3
    Ok(Pose { position: [v[12], v[13], v[14]], forward: normalise([v[8], v[9], v[10]]) })
}

/// Writes a pose in the SYNTHIA CameraParams format (camera looking along `forward`, y up).
pub fn write_synthia_pose(pose: &Pose) -> String {
    let f = normalise(pose.forward);
    let up = [0.0, 1.0, 0.0];
    let x = normalise(cross(up, f));
    let y = cross(f, x);
    let p = pose.position;
    let m = [x[0], x[1], x[2], 0.0, y[0], y[1], y[2], 0.0, f[0], f[1], f[2], 0.0, p[0], p[1], p[2], 1.0];
    m.iter().map(|v| format!("{v:.6}")).collect::<Vec<_>>().join(" ") + "\n"
}

pub(super) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

pub(super) fn normalise(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if n > 0.0 {
        [v[0] / n, v[1] / n, v[2] / n]
    } else {
        [0.0, 0.0, 1.0]
    }
}

/// Rotation matrix (row-major) of a unit quaternion (w, x, y, z).
fn quat_to_matrix(w: f64, x: f64, y: f64, z: f64) -> [[f64; 3]; 3] {
    let n = (w * w + x * x + y * y + z * z).sqrt();
    let (w, x, y, z) = (w / n, x / n, y / n, z / n);
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// Reads a pose list (one `name numbers...` line per image; `#` comments) into name -> pose.
pub fn read_pose_list(path: &Path, format: PoseFormat) -> Result<std::collections::HashMap<String, Pose>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_pose_list(&text, path, format)
}

/// [`read_pose_list`] on a file's text; `path` only names the source in errors.
pub fn parse_pose_list(text: &str, path: &Path, format: PoseFormat) -> Result<std::collections::HashMap<String, Pose>> {
    let mut out = std::collections::HashMap::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let (name, rest) = line.split_once(char::is_whitespace).unwrap_or((line, ""));
        let v = parse_numbers(rest, path, i + 1)?;
        let want = match format {
            PoseFormat::QuatCenter | PoseFormat::QuatTranslation => 7,
            _ => 16,
        };
        if v.len() != want {
            return Err(Error::dataset(path, format!("line {}: expected {want} numbers after the name, found {}", i + 1, v.len())));
        }
        let pose = match format {
            PoseFormat::QuatCenter | PoseFormat::QuatTranslation => {
                if v[..4].iter().all(|&c| c == 0.0) {
                    return Err(Error::dataset(path, format!("line {}: the rotation quaternion is zero", i + 1)));
                }
                let r = quat_to_matrix(v[0], v[1], v[2], v[3]);
                let t = [v[4], v[5], v[6]];
                // rows of a world-to-camera rotation are the camera axes in world coordinates
                let position =
                    if format == PoseFormat::QuatCenter { t } else { std::array::from_fn(|j| -(0..3).map(|k| r[k][j] * t[k]).sum::<f64>()) };
                Pose { position, forward: normalise(r[2]) }
            }
            PoseFormat::MatrixCamToWorld => Pose { position: [v[3], v[7], v[11]], forward: normalise([v[2], v[6], v[10]]) },
            PoseFormat::MatrixWorldToCam => {
                let r = [[v[0], v[1], v[2]], [v[4], v[5], v[6]], [v[8], v[9], v[10]]];
                let t = [v[3], v[7], v[11]];
                let position = std::array::from_fn(|j| -(0..3).map(|k| r[k][j] * t[k]).sum::<f64>());
                Pose { position, forward: normalise(r[2]) }
            }
        };
        out.insert(name.to_string(), pose);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::{pose_matches, GroundTruthRule};

    #[test]
    fn synthia_pose_round_trip() {
        let p = Pose { position: [1.5, 1.6, -20.25], forward: normalise([0.1, 0.0, 1.0]) };
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("p.txt");
        std::fs::write(&f, write_synthia_pose(&p)).unwrap();
        let q = read_synthia_pose(&f).unwrap();
        for i in 0..3 {
            assert!((p.position[i] - q.position[i]).abs() < 1e-6 && (p.forward[i] - q.forward[i]).abs() < 1e-5);
        }
    }

    #[test]
    fn pose_lists_and_rule() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("gt.txt");
        // identity rotation; world-to-camera translation t = -C
        std::fs::write(&f, "# comment\na.jpg 1 0 0 0 2 0 0\nb.jpg 1 0 0 0 -2 0 0\n").unwrap();
        let c = read_pose_list(&f, PoseFormat::QuatCenter).unwrap();
        let t = read_pose_list(&f, PoseFormat::QuatTranslation).unwrap();
        assert_eq!(c["a.jpg"].position, [2.0, 0.0, 0.0]);
        assert_eq!(t["a.jpg"].position, [-2.0, 0.0, 0.0]);
        assert_eq!(c["a.jpg"].forward, [0.0, 0.0, 1.0]);
        let refs = [c["a.jpg"], c["b.jpg"]];
        let q = Pose { position: [1.0, 0.0, 0.0], forward: [0.0, 0.0, 1.0] };
        assert_eq!(pose_matches(&q, &refs, &GroundTruthRule { max_distance: 1.5, max_angle_deg: None }), vec![0]);
        let turned = Pose { forward: [1.0, 0.0, 0.0], ..q };
        assert!(pose_matches(&turned, &refs, &GroundTruthRule { max_distance: 5.0, max_angle_deg: Some(30.0) }).is_empty());
        std::fs::write(&f, "a.jpg 1 0 0 nan 2 0 0\n").unwrap();
        let e = read_pose_list(&f, PoseFormat::QuatCenter).unwrap_err().to_string();
        assert!(e.contains("gt.txt") && e.contains("line 1"), "{e}");
    }
}
