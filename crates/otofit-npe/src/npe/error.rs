//! The npe layer's one error type. Variants are grouped by whose fault they are: what the
//! caller gave (an observation, a checkpoint file, a training table or settings) apart
//! from what went wrong inside, so that a service answers the first with 422 naming the
//! field and the second with 500 ([`NpeError::is_input`]).

use std::path::PathBuf;

/// Errors of loading, training, sampling and calibrating a posterior estimator.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum NpeError {
    /// The observation does not fit the model (bad input).
    #[error(transparent)]
    Observation(#[from] ObservationError),
    /// The bytes are not a usable checkpoint (bad input: a file).
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    /// A model file that cannot be used, with the reason as source (bad input).
    #[error("{} is not a usable otofit model", path.display())]
    Unusable {
        /// The model file.
        path: PathBuf,
        /// Why.
        #[source]
        source: CheckpointError,
    },
    /// A training table that cannot be read or used (bad input).
    #[error("{}: {why}", path.display())]
    Table {
        /// The file or folder at fault.
        path: PathBuf,
        /// What is wrong with it.
        why: String,
    },
    /// A table file that cannot be parsed (bad input).
    #[error(transparent)]
    Csv(#[from] crate::dataset::DatasetError),
    /// A prior parameter whose box is not valid (bad input).
    #[error(transparent)]
    Prior(#[from] super::prior::PriorError),
    /// Training settings that do not suit the data (bad input), naming the setting.
    #[error("{why}")]
    Settings {
        /// The setting (as the CLI flag's name without dashes).
        field: &'static str,
        /// What is wrong with it.
        why: String,
    },
    /// Reading or writing a file failed.
    #[error(transparent)]
    Io(#[from] crate::dataset::FileError),
    /// A record or header could not be encoded (internal).
    #[error("cannot encode the {what}: {why}")]
    Encode {
        /// `header` or `record`.
        what: &'static str,
        /// The encoder's message.
        why: String,
    },
    /// Training diverged: no epoch gave a finite validation loss (internal).
    #[error("training produced no finite validation loss (member {member})")]
    NoFiniteLoss {
        /// Ensemble member.
        member: usize,
    },
    /// The training's threads could not be started (the system refused them; internal).
    #[error("the training's threads could not be started: {why}")]
    Threads {
        /// The thread pool's message.
        why: String,
    },
}

impl NpeError {
    /// Whether the caller's input is at fault (an observation, a file, settings), as
    /// opposed to an internal failure.
    pub fn is_input(&self) -> bool {
        match self {
            NpeError::Observation(_)
            | NpeError::Checkpoint(_)
            | NpeError::Unusable { .. }
            | NpeError::Table { .. }
            | NpeError::Prior(_)
            | NpeError::Settings { .. } => true,
            NpeError::Csv(e) => e.is_input(),
            NpeError::Io(_) | NpeError::Encode { .. } | NpeError::NoFiniteLoss { .. } | NpeError::Threads { .. } => {
                false
            }
        }
    }

    pub(crate) fn table(path: impl Into<PathBuf>, why: impl Into<String>) -> NpeError {
        NpeError::Table { path: path.into(), why: why.into() }
    }

    pub(crate) fn settings(field: &'static str, why: impl Into<String>) -> NpeError {
        NpeError::Settings { field, why: why.into() }
    }
}

/// An observation the model cannot take.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ObservationError {
    /// Wrong number of features.
    #[error("observation has {got} features, the model expects {expected}")]
    FeatureCount {
        /// Features given.
        got: usize,
        /// Features the model has.
        expected: usize,
    },
    /// A parameter row of the wrong width (log-density queries).
    #[error("a parameter row has {got} values, the model has {expected} parameters")]
    ThetaWidth {
        /// Values given.
        got: usize,
        /// Parameters of the model.
        expected: usize,
    },
    /// A measure named that is none of the model's feature groups.
    #[error("unknown feature group '{name}' (the model's: {known})")]
    UnknownGroup {
        /// The name given.
        name: String,
        /// The model's groups, comma-separated.
        known: String,
    },
    /// A group's present features are not one band.
    #[error("group '{group}': the measured frequencies must form one contiguous band")]
    NotContiguous {
        /// The feature group.
        group: String,
    },
    /// A group's band is narrower than the model was trained to accept.
    #[error(
        "group '{group}': the band {lo_hz:.0}–{hi_hz:.0} Hz is narrower than this model was trained for (it must \
         reach {need_lo_hz:.0} Hz and {need_hi_hz:.0} Hz)"
    )]
    BandTooNarrow {
        /// The feature group.
        group: String,
        /// The band given.
        lo_hz: f64,
        /// The band given.
        hi_hz: f64,
        /// The band's lowest acceptable start.
        need_lo_hz: f64,
        /// The band's highest acceptable end.
        need_hi_hz: f64,
    },
    /// No feature group is complete.
    #[error("no complete feature group present (groups: {groups})")]
    NoGroup {
        /// The model's groups, comma-separated.
        groups: String,
    },
    /// A feature outside every group is absent.
    #[error("feature '{feature}' is missing")]
    Missing {
        /// The feature's name.
        feature: String,
    },
    /// A model without masks needs every feature, finite.
    #[error("feature '{feature}' is missing or not finite (this model needs every feature)")]
    MissingOrNotFinite {
        /// The feature's name.
        feature: String,
    },
}

impl ObservationError {
    /// The feature or group named by the error, if any.
    pub fn subject(&self) -> Option<&str> {
        match self {
            ObservationError::NotContiguous { group } | ObservationError::BandTooNarrow { group, .. } => Some(group),
            ObservationError::Missing { feature } | ObservationError::MissingOrNotFinite { feature } => Some(feature),
            _ => None,
        }
    }
}

/// Why a checkpoint cannot be used; every field of the header is checked.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CheckpointError {
    /// The file does not start with the magic.
    #[error("not an otofit NPE checkpoint (bad magic)")]
    BadMagic,
    /// The header length exceeds the file.
    #[error("truncated checkpoint (header length {0} exceeds the file)")]
    HeaderLength(u64),
    /// A member's record is cut short.
    #[error("truncated checkpoint (member {member} of {members})")]
    Truncated {
        /// The member.
        member: usize,
        /// Members the header declares.
        members: usize,
    },
    /// The header is not the JSON of a header.
    #[error("checkpoint header")]
    Header(#[source] serde_json::Error),
    /// A format this version does not read.
    #[error("checkpoint format {0} is not supported (this otofit reads formats 1 and {FORMAT})", FORMAT = super::FORMAT_VERSION)]
    Format(u32),
    /// The header's vectors disagree with its parameters and features.
    #[error("checkpoint header shapes disagree ({params} parameters, {features} features)")]
    Shapes {
        /// Parameters in the header.
        params: usize,
        /// Features in the header.
        features: usize,
    },
    /// The flow settings cannot be built.
    #[error(transparent)]
    Flow(#[from] crate::flow::FlowConfigError),
    /// A header field out of its range, named.
    #[error("checkpoint {field}: {why}")]
    Field {
        /// The header field.
        field: &'static str,
        /// What is wrong with it.
        why: String,
    },
    /// The weights cannot be decoded.
    #[error("weights: {0}")]
    Weights(String),
    /// No member at all.
    #[error("checkpoint has no weights")]
    NoWeights,
    /// The weights are of another architecture.
    #[error("weights do not match the architecture")]
    Architecture,
}

impl CheckpointError {
    pub(crate) fn field(field: &'static str, why: impl Into<String>) -> CheckpointError {
        CheckpointError::Field { field, why: why.into() }
    }
}
