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
    let r: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| v[4 * j + i]));
    Ok(Pose { position: [v[12], v[13], v[14]], forward: normalise([v[8], v[9], v[10]]), orientation: Some(quat_of_matrix(&r)) })
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

/// The unit quaternion `[x, y, z, w]` (w >= 0) of a rotation matrix (row-major; a matrix that is
/// not quite orthonormal gives the quaternion of its nearest rotation, near enough for poses read
/// from text). Shepperd's method: the largest of the four squared components is taken from the
/// trace, the others from off-diagonal sums, so no division is by a small number.
pub(super) fn quat_of_matrix(r: &[[f64; 3]; 3]) -> [f64; 4] {
    let t = r[0][0] + r[1][1] + r[2][2];
    let q = if t >= r[0][0].max(r[1][1]).max(r[2][2]) {
        let s = (1.0 + t).max(0.0).sqrt() * 2.0;
        [(r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s, 0.25 * s]
    } else if r[0][0] >= r[1][1] && r[0][0] >= r[2][2] {
        let s = (1.0 + r[0][0] - r[1][1] - r[2][2]).max(0.0).sqrt() * 2.0;
        [0.25 * s, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s, (r[2][1] - r[1][2]) / s]
    } else if r[1][1] >= r[2][2] {
        let s = (1.0 + r[1][1] - r[0][0] - r[2][2]).max(0.0).sqrt() * 2.0;
        [(r[0][1] + r[1][0]) / s, 0.25 * s, (r[1][2] + r[2][1]) / s, (r[0][2] - r[2][0]) / s]
    } else {
        let s = (1.0 + r[2][2] - r[0][0] - r[1][1]).max(0.0).sqrt() * 2.0;
        [(r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, 0.25 * s, (r[1][0] - r[0][1]) / s]
    };
    let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
    let sign = if q[3] < 0.0 { -1.0 } else { 1.0 };
    q.map(|c| sign * c / n)
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

fn transpose(r: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| r[j][i]))
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
                // camera-to-world is the inverse rotation: the conjugate quaternion
                Pose { position, forward: normalise(r[2]), orientation: Some(quat_of_matrix(&transpose(&r))) }
            }
            PoseFormat::MatrixCamToWorld => {
                let r = [[v[0], v[1], v[2]], [v[4], v[5], v[6]], [v[8], v[9], v[10]]];
                Pose { position: [v[3], v[7], v[11]], forward: normalise([v[2], v[6], v[10]]), orientation: Some(quat_of_matrix(&r)) }
            }
            PoseFormat::MatrixWorldToCam => {
                let r = [[v[0], v[1], v[2]], [v[4], v[5], v[6]], [v[8], v[9], v[10]]];
                let t = [v[3], v[7], v[11]];
                let position = std::array::from_fn(|j| -(0..3).map(|k| r[k][j] * t[k]).sum::<f64>());
                Pose { position, forward: normalise(r[2]), orientation: Some(quat_of_matrix(&transpose(&r))) }
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
        let p = Pose { position: [1.5, 1.6, -20.25], forward: normalise([0.1, 0.0, 1.0]), orientation: None };
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
        let q = Pose { position: [1.0, 0.0, 0.0], forward: [0.0, 0.0, 1.0], orientation: None };
        assert_eq!(pose_matches(&q, &refs, &GroundTruthRule { max_distance: 1.5, max_angle_deg: None }), vec![0]);
        let turned = Pose { forward: [1.0, 0.0, 0.0], ..q };
        assert!(pose_matches(&turned, &refs, &GroundTruthRule { max_distance: 5.0, max_angle_deg: Some(30.0) }).is_empty());
        std::fs::write(&f, "a.jpg 1 0 0 nan 2 0 0\n").unwrap();
        let e = read_pose_list(&f, PoseFormat::QuatCenter).unwrap_err().to_string();
        assert!(e.contains("gt.txt") && e.contains("line 1"), "{e}");
    }

    /// The camera's z axis under a quaternion `[x, y, z, w]`: the third column of its matrix.
    fn z_axis(q: [f64; 4]) -> [f64; 3] {
        let r = quat_to_matrix(q[3], q[0], q[1], q[2]);
        [r[0][2], r[1][2], r[2][2]]
    }

    /// Every pose-list format and the SYNTHIA matrix give the same camera-to-world orientation
    /// for one camera, its z axis the pose's forward, and the quaternion reads back to the matrix.
    #[test]
    fn orientations_agree_across_formats() {
        // camera-to-world rotation of a camera turned about three axes
        let q_cw = {
            let (w, x, y, z) = (0.8_f64, 0.3, -0.4, 0.2);
            let n = (w * w + x * x + y * y + z * z).sqrt();
            [x / n, y / n, z / n, w / n]
        };
        let r_cw = quat_to_matrix(q_cw[3], q_cw[0], q_cw[1], q_cw[2]);
        assert!(quat_of_matrix(&r_cw).iter().zip(&q_cw).all(|(a, b)| (a - b).abs() < 1e-12), "matrix -> quaternion");
        for m in [[[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]] {
            // half turns: the trace is not the largest term
            let q = quat_of_matrix(&m);
            let back = quat_to_matrix(q[3], q[0], q[1], q[2]);
            assert!((0..3).all(|i| (0..3).all(|j| (back[i][j] - m[i][j]).abs() < 1e-12)), "{m:?} -> {q:?}");
        }
        let c = [4.0, -2.0, 1.5];
        let r_wc = transpose(&r_cw);
        let t: [f64; 3] = std::array::from_fn(|i| -(0..3).map(|k| r_wc[i][k] * c[k]).sum::<f64>());
        let q_wc = [-q_cw[0], -q_cw[1], -q_cw[2], q_cw[3]];
        let row = |r: &[[f64; 3]; 3], p: [f64; 3]| {
            (0..3).flat_map(|i| [r[i][0], r[i][1], r[i][2], p[i]]).chain([0.0, 0.0, 0.0, 1.0]).map(|v| v.to_string()).collect::<Vec<_>>().join(" ")
        };
        let lines = [
            (PoseFormat::QuatCenter, format!("a {} {} {} {} {} {} {}", q_wc[3], q_wc[0], q_wc[1], q_wc[2], c[0], c[1], c[2])),
            (PoseFormat::QuatTranslation, format!("a {} {} {} {} {} {} {}", q_wc[3], q_wc[0], q_wc[1], q_wc[2], t[0], t[1], t[2])),
            (PoseFormat::MatrixCamToWorld, format!("a {}", row(&r_cw, c))),
            (PoseFormat::MatrixWorldToCam, format!("a {}", row(&r_wc, t))),
        ];
        let synthia: Vec<String> = (0..4)
            .flat_map(|j| (0..4).map(move |i| (i, j)))
            .map(|(i, j)| match (i, j) {
                (3, 3) => "1".to_string(),
                (3, _) => "0".to_string(),
                (i, 3) => c[i].to_string(),
                (i, j) => r_cw[i][j].to_string(),
            })
            .collect();
        let mut poses: Vec<(String, Pose)> =
            lines.iter().map(|(f, l)| (format!("{f:?}"), parse_pose_list(l, Path::new("x.txt"), *f).unwrap()["a"])).collect();
        poses.push(("synthia".into(), parse_synthia_pose(&synthia.join(" "), Path::new("p.txt")).unwrap()));
        for (what, p) in poses {
            let q = p.orientation.unwrap_or_else(|| panic!("{what}: no orientation"));
            assert!(q.iter().zip(&q_cw).all(|(a, b)| (a - b).abs() < 1e-9), "{what}: {q:?} against {q_cw:?}");
            assert!(p.position.iter().zip(&c).all(|(a, b)| (a - b).abs() < 1e-9), "{what}: {:?}", p.position);
            assert!(z_axis(q).iter().zip(&p.forward).all(|(a, b)| (a - b).abs() < 1e-9), "{what}: z axis and forward");
        }
    }
}
