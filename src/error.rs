//! The one error type of the crate. Every variant names the resource that failed (a file, a map,
//! a config field) and what was wrong with it, so a CLI user can act on the message alone; the
//! one exception, [`Error::Check`], is what a low-level check says before its caller names the
//! resource ([`Error::named`]).

use std::path::PathBuf;

/// Result alias used throughout the crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Non-exhaustive: a later version may add variants, so a `match` on it needs a `_` arm.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: cannot decode image: {reason}")]
    ImageDecode { path: PathBuf, reason: String },
    #[error("{path}: image is empty ({width}x{height})")]
    EmptyImage { path: PathBuf, width: u32, height: u32 },
    #[error("{labels}: label map is {label_size:?} (w, h) but image {image} is {image_size:?}")]
    SizeMismatch { image: PathBuf, labels: PathBuf, image_size: (u32, u32), label_size: (u32, u32) },
    #[error("{path}: pixel ({x}, {y}) has class id {id}, which the class table does not know (and is not void)")]
    UnknownClassId { path: PathBuf, id: u32, x: u32, y: u32 },
    #[error("{path}: pixel ({x}, {y}) has colour {rgb:?}, which is not in the class palette")]
    UnknownClassColor { path: PathBuf, rgb: [u8; 3], x: u32, y: u32 },
    #[error("{path}: unsupported label map: {reason}")]
    UnsupportedLabelFormat { path: PathBuf, reason: String },
    #[error("{image}: no label map given and no segmenter configured: give label maps, or a segmenter model")]
    NoLabels { image: PathBuf },
    #[error("config {source_name}: {reason}")]
    InvalidConfig { source_name: String, reason: String },
    #[error("map {path}: corrupt: {reason}")]
    CorruptMap { path: PathBuf, reason: String },
    #[error("map {path}: format version {found} is not supported (this build reads version {supported}){}", version_hint(*found, *supported))]
    MapVersion { path: PathBuf, found: u32, supported: u32 },
    #[error("map {map}: built with {field} = {map_value}, but the query config has {given_value}; re-encode or use the map's config")]
    IncompatibleConfig { map: PathBuf, field: String, map_value: String, given_value: String },
    #[error("map {map}: image id {id:?} is already stored")]
    DuplicateImageId { map: PathBuf, id: String },
    /// One id given to two images of one batch (before: "is already stored", of a map that
    /// held neither).
    #[error("map {map}: image id {id:?} is given twice (images {first} and {second} of those added); ids must be unique")]
    RepeatedImageId { map: PathBuf, id: String, first: usize, second: usize },
    #[error("image {id:?} refused, nothing of it written: {reason}")]
    InvalidImage { id: String, reason: String },
    #[error("dataset {path}: {reason}")]
    Dataset { path: PathBuf, reason: String },
    #[error("{what}: {reason}")]
    InvalidInput { what: String, reason: String },
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error("model {path}: {reason}")]
    Model { path: PathBuf, reason: String },
    /// A request refused for a reason the caller can act on ([`Remedy`]).
    #[error("{what}: {reason}")]
    Refused { what: String, reason: String, remedy: Remedy },
    /// Values that fail a check, said before the caller names where they come from: what the
    /// low-level checks return (`descriptors::validate`, `DescriptorSet`'s appends and layout
    /// checks, the tensor operations of `appearance::nn` and `appearance::keypoints`, the pickle
    /// and `.npy` readers, ...), which know the values but not the image, file, model or argument
    /// they belong to. A caller that knows it names it with [`Error::named`] (its message is then
    /// that variant's, with this reason); the message alone is the reason.
    #[error("{reason}")]
    Check { reason: String },
}

/// What a caller can do about a refused request, in no front end's words: messages speak of the
/// API (a map, a build, label maps); each front end words the remedy in its own terms (the
/// command line names its flags, `cli::hint`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Remedy {
    /// Append to the map, continue its interrupted build, or replace it.
    AddResumeOrReplace,
    /// Continue the interrupted build, or replace what is there.
    ResumeOrReplace,
    /// Build the map first, or continue its interrupted build.
    BuildOrResume,
    /// Give label maps, or a segmenter model.
    GiveLabels,
    /// Give the RGB images, or encode without appearance.
    GiveImagesOrNoAppearance,
    /// Name the ONNX keypoint model.
    GiveKeypointModel,
    /// Build the map with smaller segments (more of them).
    SmallerSegments,
    /// Name the dataset's reference traversal.
    NameReferenceTraversal,
    /// Name the folder image names are relative to (hloc's image root).
    NameImageRoot,
    /// Build the map again with label maps or a segmenter (it was built without labels).
    RebuildWithLabels,
    /// Build the map again with the HOG baseline's descriptors stored.
    RebuildWithHog,
    /// Skip the images the map holds already (an interrupted add or build goes on).
    SkipStored,
}

/// What a map of format `found` lacks, and how to get a readable one.
fn version_hint(found: u32, supported: u32) -> String {
    match (found, supported) {
        (3, 4) => ": it holds no verification keypoints, which only the images can give; build the map again from its images (its descriptors cannot be migrated)".into(),
        (f, s) if f > s => ": it was written by a newer semlook".into(),
        _ => ": build the map again from its images".into(),
    }
}

/// Short constructors for the common variants.
impl Error {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io { path: path.into(), source }
    }
    pub fn corrupt(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Error::CorruptMap { path: path.into(), reason: reason.into() }
    }
    pub fn dataset(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Error::Dataset { path: path.into(), reason: reason.into() }
    }
    pub fn invalid(what: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::InvalidInput { what: what.into(), reason: reason.into() }
    }
    pub fn refused(what: impl Into<String>, reason: impl Into<String>, remedy: Remedy) -> Self {
        Error::Refused { what: what.into(), reason: reason.into(), remedy }
    }
    /// A failed check, not yet named ([`Error::Check`]).
    pub fn check(reason: impl Into<String>) -> Self {
        Error::Check { reason: reason.into() }
    }
    /// Names what a failed [`Error::Check`] was about: `name` makes the error of its reason (e.g.
    /// `|reason| Error::Model { path, reason }`); any other error, which names its resource
    /// already, is returned as it is.
    pub fn named(self, name: impl FnOnce(String) -> Error) -> Error {
        match self {
            Error::Check { reason } => name(reason),
            other => other,
        }
    }
    /// What the caller can do about this error, where the engine knows.
    pub fn remedy(&self) -> Option<Remedy> {
        match self {
            Error::Refused { remedy, .. } => Some(*remedy),
            Error::NoLabels { .. } => Some(Remedy::GiveLabels),
            Error::DuplicateImageId { .. } => Some(Remedy::SkipStored),
            _ => None,
        }
    }
}

/// What went wrong on the GPU path (`crate::gpu`): defined here, below every stage, so that the
/// error enum imports no stage.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("no GPU adapter found{0}")]
    NoAdapter(String),
    #[error("adapter {adapter}: cannot create a device: {reason}")]
    Device { adapter: String, reason: String },
    #[error("GPU device lost: {0}")]
    DeviceLost(String),
    #[error("GPU out of memory while {0}")]
    OutOfMemory(String),
    #[error("adapter {adapter}: {what} needs {needed} but the limit is {available}")]
    LimitsTooSmall { adapter: String, what: String, needed: u64, available: u64 },
    #[error("shader {name}: {message}")]
    Shader { name: String, message: String },
    #[error("GPU error while {what}: {reason}")]
    Failed { what: String, reason: String },
}
