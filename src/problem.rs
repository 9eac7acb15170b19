//! The error vocabulary, with no HTTP in it: one [`Code`] per kind of failure, each with the status
//! and title a problem of that kind carries, the [`ErrorCode`] trait every error type of the crate
//! implements, and the RFC 9457 [`Problem`] object (serde only) that failed jobs store and the API
//! renders. A leaf module: it imports nothing of the crate, so every layer can name its failures.
//! A misspelt code is a compile error; the table in docs/service.md is checked by a test.

use serde::{Deserialize, Serialize};

macro_rules! codes {
    ($($(#[$doc:meta])* $variant:ident = ($name:literal, $status:literal, $title:literal),)*) => {
        /// A stable machine code: the `code` of every problem this crate emits.
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
        pub enum Code {
            $($(#[$doc])* $variant,)*
        }

        impl Code {
            /// Every code, in table order.
            pub const ALL: &'static [Code] = &[$(Code::$variant,)*];

            /// The code as it appears in a problem's `code` and `type`.
            pub const fn name(self) -> &'static str {
                match self { $(Code::$variant => $name,)* }
            }

            /// The HTTP status a problem of this code carries.
            pub const fn status(self) -> u16 {
                match self { $(Code::$variant => $status,)* }
            }

            /// A short, human title.
            pub const fn title(self) -> &'static str {
                match self { $(Code::$variant => $title,)* }
            }
        }
    };
}

codes! {
    // Request shape.
    BadRequest = ("bad_request", 400, "Bad request"),
    InvalidJson = ("invalid_json", 400, "Invalid JSON"),
    InvalidMultipart = ("invalid_multipart", 400, "Invalid multipart body"),
    InvalidQuery = ("invalid_query", 400, "Invalid query parameter"),
    InvalidHeader = ("invalid_header", 400, "Invalid header"),
    InvalidId = ("invalid_id", 404, "No such inspection"),
    RouteNotFound = ("route_not_found", 404, "No such route"),
    NotFound = ("not_found", 404, "Not found"),
    MethodNotAllowed = ("method_not_allowed", 405, "Method not allowed"),
    OriginNotAllowed = ("origin_not_allowed", 403, "Origin not allowed"),
    Unauthorized = ("unauthorized", 401, "API key required"),
    InvalidKey = ("invalid_key", 401, "Invalid API key"),
    InsufficientScope = ("insufficient_scope", 403, "Insufficient scope"),
    NotAcceptable = ("not_acceptable", 406, "Not acceptable"),
    RequestTimeout = ("request_timeout", 408, "Request timeout"),
    BodyTooLarge = ("body_too_large", 413, "Body too large"),
    UriTooLong = ("uri_too_long", 414, "URI too long"),
    UnsupportedMediaType = ("unsupported_media_type", 415, "Unsupported media type"),
    HostNotAllowed = ("host_not_allowed", 421, "Host not allowed"),
    HeadersTooLarge = ("headers_too_large", 431, "Request headers too large"),
    InvalidOption = ("invalid_option", 422, "Invalid option"),
    OptionOutOfRange = ("option_out_of_range", 422, "Option out of range"),
    InvalidCmm = ("invalid_cmm", 422, "Invalid CMM measurements"),
    IdempotencyKeyReused = ("idempotency_key_reused", 422, "Idempotency-Key reused"),
    InspectionNotSucceeded = ("inspection_not_succeeded", 409, "Inspection has no results"),
    InspectionFinished = ("inspection_finished", 409, "Inspection already finished"),
    CmmNotFound = ("cmm_not_found", 404, "No CMM measurements"),
    ResultExpired = ("result_expired", 410, "Result deleted by retention"),
    UnknownDesignation = ("unknown_designation", 404, "Unknown connection designation"),
    UnknownModel = ("unknown_model", 422, "Unknown model"),
    CallbackNotAllowed = ("callback_not_allowed", 422, "Callback destination not allowed"),
    // Stations and their qualification.
    UnknownStation = ("unknown_station", 422, "Unknown station"),
    StationNotFound = ("station_not_found", 404, "No such station"),
    StationExists = ("station_exists", 409, "Station already exists"),
    MasterExists = ("master_exists", 409, "Master already uploaded"),
    InvalidCertificate = ("invalid_certificate", 422, "Invalid certificate"),
    StudyRefused = ("study_refused", 422, "Study cannot be run"),
    CheckRefused = ("check_refused", 422, "Check cannot be charted"),
    CheckExists = ("check_exists", 409, "Inspection already charted"),
    // Bundle validation (the bundle reader's codes).
    UnsupportedFormatVersion = ("unsupported_format_version", 422, "Unsupported bundle format"),
    InvalidManifest = ("invalid_manifest", 422, "Invalid manifest"),
    InvalidOptics = ("invalid_optics", 422, "Invalid optics"),
    UnknownConnection = ("unknown_connection", 422, "Unknown connection"),
    InvalidThread = ("invalid_thread", 422, "Invalid thread"),
    TooFewFrames = ("too_few_frames", 422, "Too few frames"),
    InvalidOffsets = ("invalid_offsets", 422, "Invalid focus offsets"),
    MissingFile = ("missing_file", 422, "Missing file"),
    UnreadableFrame = ("unreadable_frame", 422, "Unreadable frame"),
    InconsistentFrames = ("inconsistent_frames", 422, "Inconsistent frames"),
    UnsafePath = ("unsafe_path", 422, "Unsafe path"),
    BundleTooLarge = ("bundle_too_large", 413, "Bundle too large"),
    InspectionTooLarge = ("inspection_too_large", 422, "Inspection too large"),
    InvalidArchive = ("invalid_archive", 422, "Invalid archive"),
    StationOutOfRange = ("station_out_of_range", 422, "Station out of range"),
    // Job failures (in a failed inspection's `error`).
    NoDepth = ("no_depth", 422, "No depth recovered"),
    NoThread = ("no_thread", 422, "No thread found"),
    MeshFailed = ("mesh_failed", 422, "Mesh failed"),
    PipelinePanic = ("pipeline_panic", 500, "Pipeline crashed"),
    AttemptsExhausted = ("attempts_exhausted", 500, "Attempts exhausted"),
    JobPoisonous = ("job_poisonous", 500, "Job kills its worker"),
    UploadMissing = ("upload_missing", 500, "Upload missing"),
    // Server side.
    IoError = ("io_error", 500, "I/O error"),
    InternalError = ("internal_error", 500, "Internal error"),
    NotReady = ("not_ready", 503, "Not ready"),
    ModelUnavailable = ("model_unavailable", 503, "Learned model unavailable"),
    TooManyUploads = ("too_many_uploads", 429, "Too many uploads from this client"),
    TooManySubmissions = ("too_many_submissions", 429, "Too many submissions with this key"),
    ServerBusy = ("server_busy", 503, "Too many uploads at once"),
    InsufficientStorage = ("insufficient_storage", 507, "Insufficient storage"),
}

impl Code {
    /// The problem `type` URI of this code.
    pub fn type_uri(self) -> String {
        format!("tag:crestscan,2026:problem/{}", self.name())
    }

    /// Whether a job that failed with this code may succeed when run again (the failure was the
    /// server's, not the input's).
    pub fn is_transient(self) -> bool {
        self == Code::IoError
    }
}

impl std::fmt::Display for Code {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// What every error type of the crate says about itself: its code, and the field, file, header or
/// parameter at fault where there is one. The message is the error's `Display`.
pub trait ErrorCode: std::fmt::Display {
    fn code(&self) -> Code;

    fn culprit(&self) -> Option<String> {
        None
    }
}

/// The RFC 9457 problem object.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Problem {
    /// `tag:crestscan,2026:problem/{code}`.
    #[serde(rename = "type")]
    pub type_: String,
    pub title: String,
    pub status: u16,
    pub detail: String,
    /// Stable machine code; see the code table in docs/service.md.
    pub code: String,
    /// The request path (for HTTP errors).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
    /// The field, file or parameter at fault, when one is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub culprit: Option<String>,
}

impl Problem {
    pub fn new(code: Code, detail: impl Into<String>, culprit: Option<String>) -> Self {
        Self {
            type_: code.type_uri(),
            title: code.title().into(),
            status: code.status(),
            detail: detail.into(),
            code: code.name().into(),
            instance: None,
            culprit,
        }
    }

    /// The problem an error describes: its code, its message as the detail, its culprit.
    pub fn of(e: &(impl ErrorCode + ?Sized)) -> Self {
        Self::new(e.code(), e.to_string(), e.culprit())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_code_name_is_unique_snake_case_and_has_a_status_and_title() {
        let mut names: Vec<&str> = Code::ALL.iter().map(|c| c.name()).collect();
        names.sort();
        let n = names.len();
        names.dedup();
        assert_eq!(names.len(), n, "duplicate code name");
        for code in Code::ALL {
            assert!(code.name().chars().all(|c| c.is_ascii_lowercase() || c == '_'), "{code}");
            assert!((400..600).contains(&code.status()), "{code}");
            assert!(!code.title().is_empty(), "{code}");
        }
    }

    #[test]
    fn a_problem_carries_its_codes_type_title_and_status() {
        let p = Problem::new(Code::MissingFile, "a/0.png: file not found", Some("a/0.png".into()));
        assert_eq!(p.type_, "tag:crestscan,2026:problem/missing_file");
        assert_eq!((p.status, p.title.as_str(), p.code.as_str()), (422, "Missing file", "missing_file"));
        assert_eq!(p.culprit.as_deref(), Some("a/0.png"));
    }
}
