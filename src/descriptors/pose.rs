//! Where a place's image was taken ([`PlacePose`]): metadata a map stores beside the descriptors
//! of a place, and the row it is stored as. Matching never reads it.

/// Where a place's image was taken: the camera pose a dataset or a pose list gave it, stored in
/// the map beside its descriptors and published by the ROS 2 node (`geometry_msgs/PoseStamped`).
/// Matching never reads it.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PlacePose {
    /// Camera centre in the dataset's world frame (its units, usually metres).
    pub position: [f64; 3],
    /// Camera-to-world rotation, a unit quaternion `[x, y, z, w]` (ROS order); none where the
    /// source gives a position alone.
    pub orientation: Option<[f64; 4]>,
}

impl PlacePose {
    /// How far a stored quaternion's norm may be from 1 (poses are written normalised; text pose
    /// lists carry 6 to 9 digits).
    pub const UNIT_TOLERANCE: f64 = 1e-6;

    /// The stored row: `x y z qx qy qz qw`, the quaternion NaN where there is none.
    pub fn to_row(&self) -> [f64; 7] {
        let q = self.orientation.unwrap_or([f64::NAN; 4]);
        [self.position[0], self.position[1], self.position[2], q[0], q[1], q[2], q[3]]
    }

    /// A stored row back: `None` for a row of NaN (an image without a pose); an error for a
    /// position that is not finite, a quaternion half given, or one not of unit length.
    pub fn from_row(r: &[f64]) -> std::result::Result<Option<PlacePose>, PoseRowError> {
        let [x, y, z, qx, qy, qz, qw] = <[f64; 7]>::try_from(r).map_err(|_| PoseRowError::Length(r.len()))?;
        if r.iter().all(|v| v.is_nan()) {
            return Ok(None);
        }
        if ![x, y, z].iter().all(|v| v.is_finite()) {
            return Err(PoseRowError::Position([x, y, z]));
        }
        let q = [qx, qy, qz, qw];
        let orientation = if q.iter().all(|v| v.is_nan()) {
            None
        } else {
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            if !q.iter().all(|v| v.is_finite()) || (n - 1.0).abs() > Self::UNIT_TOLERANCE {
                return Err(PoseRowError::Orientation(q));
            }
            Some(q)
        };
        Ok(Some(PlacePose { position: [x, y, z], orientation }))
    }
}

/// Why a stored pose row is no [`PlacePose`].
#[derive(Debug, Clone, PartialEq)]
pub enum PoseRowError {
    /// A row of this many values, not 7.
    Length(usize),
    /// A position that is not finite.
    Position([f64; 3]),
    /// A quaternion half given, not finite, or not of unit length.
    Orientation([f64; 4]),
}

impl std::fmt::Display for PoseRowError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PoseRowError::Length(n) => write!(f, "a pose row of {n} values, not 7"),
            PoseRowError::Position(p) => write!(f, "pose position {p:?} is not finite"),
            PoseRowError::Orientation(q) => write!(f, "pose orientation {q:?} is not a unit quaternion"),
        }
    }
}

impl std::error::Error for PoseRowError {}
