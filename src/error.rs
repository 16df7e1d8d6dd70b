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
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file that failed.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// An image file could not be decoded.
    #[error("{path}: cannot decode image: {reason}")]
    ImageDecode {
        /// The image file.
        path: PathBuf,
        /// What the decoder said.
        reason: String,
    },
    /// An image (or label map) has no pixels.
    #[error("{path}: image is empty ({width}x{height})")]
    EmptyImage {
        /// The image file.
        path: PathBuf,
        /// Its width in pixels.
        width: u32,
        /// Its height in pixels.
        height: u32,
    },
    /// A label map's size differs from its image's.
    #[error("{labels}: label map is {label_size:?} (w, h) but image {image} is {image_size:?}")]
    SizeMismatch {
        /// The image file.
        image: PathBuf,
        /// The label map file.
        labels: PathBuf,
        /// The image's size in pixels, (width, height).
        image_size: (u32, u32),
        /// The label map's size in pixels, (width, height).
        label_size: (u32, u32),
    },
    /// A label map pixel holds a class id the class table does not know.
    #[error("{path}: pixel ({x}, {y}) has class id {id}, which the class table does not know (and is not void)")]
    UnknownClassId {
        /// The label map file.
        path: PathBuf,
        /// The unknown class id.
        id: u32,
        /// The pixel's column.
        x: u32,
        /// The pixel's row.
        y: u32,
    },
    /// A colour label map pixel holds a colour the class palette does not know.
    #[error("{path}: pixel ({x}, {y}) has colour {rgb:?}, which is not in the class palette")]
    UnknownClassColor {
        /// The label map file.
        path: PathBuf,
        /// The unknown colour, RGB.
        rgb: [u8; 3],
        /// The pixel's column.
        x: u32,
        /// The pixel's row.
        y: u32,
    },
    /// A label map's pixel format cannot hold class ids, or is not the one asked for.
    #[error("{path}: unsupported label map: {reason}")]
    UnsupportedLabelFormat {
        /// The label map file.
        path: PathBuf,
        /// What is wrong with its format.
        reason: String,
    },
    /// An image has neither a label map nor a segmenter to make one.
    #[error("{image}: no label map given and no segmenter configured: give label maps, or a segmenter model")]
    NoLabels {
        /// The image file.
        image: PathBuf,
    },
    /// A config is malformed or one of its values is out of range.
    #[error("config {source_name}: {reason}")]
    InvalidConfig {
        /// Where the config came from (a file name, or a description of the source).
        source_name: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A stored map cannot be read as written.
    #[error("map {path}: corrupt: {reason}")]
    CorruptMap {
        /// The map directory or file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// A file of a map's approximate index is missing or fails its checks. The index is built
    /// from the map's own descriptors, so building it again (`map::index::build`) or dropping it
    /// (`map::index::drop_index`) mends the map ([`Remedy::RebuildIndex`]).
    #[error("map index file {path}: {reason} (a file of the map's index: build the index again, or drop it)")]
    DamagedIndex {
        /// The index file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
        /// Whether the file is missing (not there at all).
        missing: bool,
    },
    /// A stored map has a format version this build does not read.
    #[error("map {path}: format version {found} is not supported (this build reads version {supported}){}", version_hint(*found, *supported))]
    MapVersion {
        /// The map directory or file.
        path: PathBuf,
        /// The version the map was written with.
        found: u32,
        /// The version this build reads.
        supported: u32,
    },
    /// The query config differs from the map's in a field both must agree on.
    #[error("map {map}: built with {field} = {map_value}, but the query config has {given_value}; re-encode or use the map's config")]
    IncompatibleConfig {
        /// The map.
        map: PathBuf,
        /// The config field that differs.
        field: String,
        /// The field's value in the map's config.
        map_value: String,
        /// The field's value in the given config.
        given_value: String,
    },
    /// An image id added to a map is stored in it already.
    #[error("map {map}: image id {id:?} is already stored")]
    DuplicateImageId {
        /// The map.
        map: PathBuf,
        /// The image id.
        id: String,
    },
    /// One id given to two images of one batch (before: "is already stored", of a map that
    /// held neither).
    #[error("map {map}: image id {id:?} is given twice (images {first} and {second} of those added); ids must be unique")]
    RepeatedImageId {
        /// The map.
        map: PathBuf,
        /// The image id.
        id: String,
        /// The index of the first image with it, among those added (from 0).
        first: usize,
        /// The index of the second image with it, among those added (from 0).
        second: usize,
    },
    /// An image given to a map fails a check, and nothing of it was written.
    #[error("image {id:?} refused, nothing of it written: {reason}")]
    InvalidImage {
        /// The image id.
        id: String,
        /// What is wrong with the image.
        reason: String,
    },
    /// A dataset's files or layout are missing or malformed.
    #[error("dataset {path}: {reason}")]
    Dataset {
        /// The dataset's directory or file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// An argument or input value is invalid.
    #[error("{what}: {reason}")]
    InvalidInput {
        /// What the value is (an argument, a file, an image).
        what: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The GPU path failed.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// A model file cannot be loaded or run, or its outputs are wrong.
    #[error("model {path}: {reason}")]
    Model {
        /// The model file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A request refused for a reason the caller can act on ([`Remedy`]).
    #[error("{what}: {reason}")]
    Refused {
        /// What was refused (the map, the build, the argument).
        what: String,
        /// Why it was refused.
        reason: String,
        /// What the caller can do about it.
        remedy: Remedy,
    },
    /// Values that fail a check, said before the caller names where they come from: what the
    /// low-level checks return (`descriptors::validate`, `DescriptorSet`'s appends and layout
    /// checks, the tensor operations of `nn::conv` and `appearance::keypoints`, the pickle
    /// and `.npy` readers, ...), which know the values but not the image, file, model or argument
    /// they belong to. A caller that knows it names it with [`Error::named`] (its message is then
    /// that variant's, with this reason); the message alone is the reason.
    #[error("{reason}")]
    Check {
        /// Why the values fail the check.
        reason: String,
    },
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
    /// Skip the images the map holds already (an interrupted add or build goes on), or store the
    /// new ones under other ids.
    SkipStored,
    /// Build the map's approximate index again (from the map), or drop it.
    RebuildIndex,
    /// Skip the images that fail to load (and report them) instead of stopping.
    SkipInvalid,
    /// Wait for the build of the map that another process is running, then ask again.
    WaitForBuild,
    /// Continue the interrupted build with the layout it had (its HOG descriptors, its value type).
    ResumeWithSameLayout,
    /// Build no approximate index: the map has no appearance vectors to index.
    NoIndexWithoutAppearance,
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
    /// An [`Error::Io`] on `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io { path: path.into(), source }
    }
    /// An [`Error::CorruptMap`] of the map at `path`.
    pub fn corrupt(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Error::CorruptMap { path: path.into(), reason: reason.into() }
    }
    /// An [`Error::Dataset`] of the dataset at `path`.
    pub fn dataset(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Error::Dataset { path: path.into(), reason: reason.into() }
    }
    /// An [`Error::InvalidInput`] about `what`.
    pub fn invalid(what: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::InvalidInput { what: what.into(), reason: reason.into() }
    }
    /// An [`Error::Refused`] of `what`, with what the caller can do about it.
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
            Error::DamagedIndex { .. } => Some(Remedy::RebuildIndex),
            Error::ImageDecode { .. } | Error::EmptyImage { .. } => Some(Remedy::SkipInvalid),
            _ => None,
        }
    }
    /// This error as an [`Error::DamagedIndex`] where it is about a file of a map's index: an I/O
    /// error on it, or a failed check naming it ([`Error::CorruptMap`]); any other as it is. For
    /// the readers of index files, which know the file is one.
    pub fn in_index(self) -> Error {
        match self {
            Error::Io { path, source } => {
                Error::DamagedIndex { reason: source.to_string(), missing: source.kind() == std::io::ErrorKind::NotFound, path }
            }
            Error::CorruptMap { path, reason } => Error::DamagedIndex { path, reason, missing: false },
            other => other,
        }
    }
    /// Whether this error says a file is not there: an I/O error "not found", or an index file
    /// missing ([`Error::DamagedIndex`]).
    pub fn is_missing_file(&self) -> bool {
        match self {
            Error::Io { source, .. } => source.kind() == std::io::ErrorKind::NotFound,
            Error::DamagedIndex { missing, .. } => *missing,
            _ => false,
        }
    }
    /// What kind of error this is, for a program to tell errors apart without reading messages:
    /// the Python exception's class and the `kind` of the command line's JSON refusals.
    pub fn kind(&self) -> ErrorKind {
        match self {
            e if e.is_missing_file() => ErrorKind::MissingFile,
            Error::Io { .. }
            | Error::ImageDecode { .. }
            | Error::EmptyImage { .. }
            | Error::UnknownClassId { .. }
            | Error::UnknownClassColor { .. }
            | Error::UnsupportedLabelFormat { .. }
            | Error::SizeMismatch { .. }
            | Error::NoLabels { .. } => ErrorKind::InputFile,
            Error::InvalidConfig { .. } => ErrorKind::InvalidConfig,
            // a file of a map's index that is there but damaged: as any damaged map file
            Error::CorruptMap { .. } | Error::DamagedIndex { .. } => ErrorKind::CorruptMap,
            Error::MapVersion { .. } => ErrorKind::MapVersion,
            Error::IncompatibleConfig { .. } => ErrorKind::IncompatibleConfig,
            Error::DuplicateImageId { .. } | Error::RepeatedImageId { .. } => ErrorKind::DuplicateImageId,
            Error::InvalidImage { .. } => ErrorKind::InvalidImage,
            Error::Dataset { .. } => ErrorKind::Dataset,
            // a refusal is about what was asked; a check its caller did not name, a bad value all the same
            Error::InvalidInput { .. } | Error::Refused { .. } | Error::Check { .. } => ErrorKind::InvalidInput,
            Error::Model { .. } => ErrorKind::Model,
            Error::Gpu(_) => ErrorKind::Gpu,
        }
    }
}

/// The kinds of [`Error`] a program tells apart ([`Error::kind`]), each with a stable name
/// ([`ErrorKind::name`]): what the Python exceptions' classes and the command line's JSON
/// refusals say.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ErrorKind {
    /// A file or folder that does not exist.
    MissingFile,
    /// An image or label file that cannot be read or decoded, or whose content is not usable.
    InputFile,
    /// A configuration value out of range or unreadable.
    InvalidConfig,
    /// A map file that fails its checks.
    CorruptMap,
    /// A map written by an unsupported format version.
    MapVersion,
    /// Queries encoded differently from the map.
    IncompatibleConfig,
    /// An image id the map already stores, or one given to two images.
    DuplicateImageId,
    /// Descriptors refused before anything was written.
    InvalidImage,
    /// A dataset folder, manifest or ground-truth file that cannot be used.
    Dataset,
    /// An argument or request the engine cannot serve (refusals included).
    InvalidInput,
    /// A model file that is missing, of the wrong kind, or fails to run.
    Model,
    /// A failure of the GPU backend.
    Gpu,
}

impl ErrorKind {
    /// Every kind, in the order of the declaration.
    pub const ALL: [ErrorKind; 12] = [
        ErrorKind::MissingFile,
        ErrorKind::InputFile,
        ErrorKind::InvalidConfig,
        ErrorKind::CorruptMap,
        ErrorKind::MapVersion,
        ErrorKind::IncompatibleConfig,
        ErrorKind::DuplicateImageId,
        ErrorKind::InvalidImage,
        ErrorKind::Dataset,
        ErrorKind::InvalidInput,
        ErrorKind::Model,
        ErrorKind::Gpu,
    ];
    /// The kind's stable name (snake case: `missing_file`, `input_file`, ...).
    pub fn name(self) -> &'static str {
        match self {
            ErrorKind::MissingFile => "missing_file",
            ErrorKind::InputFile => "input_file",
            ErrorKind::InvalidConfig => "invalid_config",
            ErrorKind::CorruptMap => "corrupt_map",
            ErrorKind::MapVersion => "map_version",
            ErrorKind::IncompatibleConfig => "incompatible_config",
            ErrorKind::DuplicateImageId => "duplicate_image_id",
            ErrorKind::InvalidImage => "invalid_image",
            ErrorKind::Dataset => "dataset",
            ErrorKind::InvalidInput => "invalid_input",
            ErrorKind::Model => "model",
            ErrorKind::Gpu => "gpu",
        }
    }
}

/// What went wrong on the GPU path (`crate::gpu`): defined here, below every stage, so that the
/// error enum imports no stage.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No usable GPU adapter, or not the one asked for; the field holds the rest of the message
    /// (the adapters seen, or how to install a driver), empty or starting with a separator.
    #[error("no GPU adapter found{0}")]
    NoAdapter(String),
    /// The adapter would not create a device.
    #[error("adapter {adapter}: cannot create a device: {reason}")]
    Device {
        /// The adapter's name.
        adapter: String,
        /// What the driver said.
        reason: String,
    },
    /// The device was lost; the field holds what was going on, or the driver's message.
    #[error("GPU device lost: {0}")]
    DeviceLost(String),
    /// The GPU ran out of memory; the field holds what was going on.
    #[error("GPU out of memory while {0}")]
    OutOfMemory(String),
    /// A device limit is too small for the work asked for.
    #[error("adapter {adapter}: {what} needs {needed} but the limit is {available}")]
    LimitsTooSmall {
        /// The adapter's name.
        adapter: String,
        /// What needs more (the limit and the work).
        what: String,
        /// What the work needs, in the limit's units.
        needed: u64,
        /// What the device allows, in the limit's units.
        available: u64,
    },
    /// A shader failed to preprocess or compile.
    #[error("shader {name}: {message}")]
    Shader {
        /// The shader's name (its file, and entry point where known).
        name: String,
        /// What the preprocessor or compiler said.
        message: String,
    },
    /// Any other GPU error.
    #[error("GPU error while {what}: {reason}")]
    Failed {
        /// What was going on (e.g. "reading back").
        what: String,
        /// What went wrong.
        reason: String,
    },
}
