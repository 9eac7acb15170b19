//! An OPC UA server on OPC 40100-1 (OPC UA for Machine Vision), `opcua_endpoint`
//! (docs/interchange.md, "OPC UA"). The companion specification's NodeSet (`data/opcua/`, its
//! namespace [`MV_NAMESPACE`]) is loaded at start; crestscan's instances and its own additions
//! are in the namespace [`NAMESPACE`]. Under `Objects/VisionSystem` (a `VisionSystemType`):
//!
//! - `VisionStateMachine` (`VisionStateMachineType`), its `CurrentState` (with `Id`, the
//!   specification's state node): `Preoperational` until the first look at the store,
//!   `Operational` while the store reads and takes writes, `Error` (with crestscan's
//!   `ErrorReason`) while it does not, `Halted` once the service is stopping; crestscan's
//!   `ExecutionState` beside it: `Ready` (nothing queued or running) or `Executing`, with the
//!   queued and running inspections counted;
//! - `RecipeManagement/Recipes/default`: the pipeline options a submission gets unless it overrides
//!   them (`Content`, JSON);
//! - `ConfigurationManagement/Configurations/<station>`: each station's status (qualified,
//!   suspended, …) and its reason;
//! - `ResultManagement/LastResult`: the last succeeded inspection's result, and the two result
//!   methods;
//! - events of crestscan's `ThreadResultReadyEventType`, a subtype of the specification's
//!   `ResultReadyEventType` (the VisionSystem is their source and notifier; the Server object sees
//!   them too), for each succeeded inspection: the specification's fields (`ResultId`, `JobId`,
//!   `PartId`, the recipe and configuration ids as its structures, `ResultState`, …) and
//!   crestscan's: verdict, decision, review flag, station, serial, connection, report link, and per
//!   thread its number, mean height, uncertainty, finding and black-crest length.
//!
//! Of the specification's methods, ResultManagement's `GetResultById` and
//! `GetResultListFiltered` answer from the last results announced; the state machine's (`Halt`,
//! `Reset`) and recipe and configuration management are not offered: the state follows the store,
//! and a submission carries its own options.
//!
//! Each process serving the API with an endpoint follows the database's `events` table (as the MQTT
//! publisher does, but every server sees every event), so results another process finished are
//! announced too. Anonymous sessions are refused when the service requires API keys; a client then
//! presents a user name token whose password is an API key with the `read` scope.

use crate::service::auth::{self, Scope};
use crate::service::config::{AuthMode, Settings};
use crate::service::opcua_settings::Endpoint;
use crate::service::store::{InspectionRow, Store, StoreError};
use opcua::Event;
use opcua::crypto::SecurityPolicy;
use opcua::nodes::{BaseEventType, NodeSet2Import};
use opcua::server::address_space::{AddressSpace, EventNotifier, ObjectBuilder, ObjectTypeBuilder, VariableBuilder};
use opcua::server::authenticator::{AuthManager, Password, UserToken, user_pass_security_policy_id};
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::memory::{SimpleNodeManager, simple_node_manager, simple_node_manager_imports};
use opcua::server::{ANONYMOUS_USER_TOKEN_ID, Server, ServerBuilder, ServerEndpoint, ServerHandle};
use opcua::types::{
    BuildInfo, ByteString, DataTypeId, DataValue, DateTime, Error as UaError, ExpandedNodeId, ExtensionObject,
    LocalizedText, MessageSecurityMode, NodeId, ObjectId, ObjectTypeId, QualifiedName, StatusCode, UAString,
    UserTokenPolicy, UserTokenType, VariableTypeId, Variant,
};
use sha2::{Digest, Sha256};
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::watch;

/// The namespace of crestscan's nodes and types.
pub const NAMESPACE: &str = "urn:crestscan:machine-vision";
/// OPC 40100-1's namespace, its NodeSet's model.
pub const MV_NAMESPACE: &str = "http://opcfoundation.org/UA/MachineVision";
/// OPC 40100-1's NodeSet, compiled in (data/opcua/SOURCE.md).
const MV_NODESET: &str = include_str!("../../data/opcua/Opc.Ua.MachineVision.NodeSet2.xml");
/// The node managers' names: the specification's types, crestscan's instances.
const MV_MANAGER: &str = "machine-vision";
const OWN_MANAGER: &str = "crestscan";
/// How often the server looks for new events.
const POLL: Duration = Duration::from_millis(500);
/// How often it checks that the store reads and takes a write (the check commits a row, so not at
/// every poll).
const HEALTH: Duration = Duration::from_secs(5);
/// Events read at a time.
const BATCH: i64 = 100;
/// Results `GetResultById` answers from: the last this many announced.
const RECENT_RESULTS: usize = 1000;
/// `GetResultById`'s Error when the result is not among them (negative: the application's own).
const RESULT_NOT_HELD: i32 = -1;

/// What the result methods answer from: the results announced last (newest at the back) and the
/// next handle. A handle only names a call's answer (there is no file transfer to release), but is
/// unique in this server, as the specification asks.
#[derive(Default)]
struct Held {
    recent: std::sync::Mutex<std::collections::VecDeque<ResultDataType>>,
    next_handle: std::sync::atomic::AtomicU32,
}

impl Held {
    fn handle(&self) -> Variant {
        Variant::UInt32(self.next_handle.fetch_add(1, std::sync::atomic::Ordering::Relaxed).wrapping_add(1))
    }

    fn results(&self) -> std::sync::MutexGuard<'_, std::collections::VecDeque<ResultDataType>> {
        self.recent.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Keeps a result: once, at the back (an event read again after a failed read is announced
    /// again), the oldest dropped past [`RECENT_RESULTS`].
    fn hold(&self, result: ResultDataType) {
        let mut recent = self.results();
        recent.retain(|r| r.result_id != result.result_id);
        if recent.len() == RECENT_RESULTS {
            recent.pop_front();
        }
        recent.push_back(result);
    }
}

/// Numeric node ids in OPC 40100-1's NodeSet (its namespace).
mod mv {
    pub const VISION_SYSTEM_TYPE: u32 = 1003;
    pub const RECIPE_MANAGEMENT_TYPE: u32 = 1004;
    pub const CONFIGURATION_MANAGEMENT_TYPE: u32 = 1006;
    pub const RESULT_MANAGEMENT_TYPE: u32 = 1007;
    pub const RECIPE_FOLDER_TYPE: u32 = 1008;
    pub const CONFIGURATION_FOLDER_TYPE: u32 = 1011;
    pub const VISION_STATE_MACHINE_TYPE: u32 = 1017;
    pub const RESULT_READY_EVENT_TYPE: u32 = 1024;
    /// VisionStateMachineType's states (their StateNumber 1 to 4).
    pub const STATES: [(&str, u32); 4] =
        [("Preoperational", 5028), ("Halted", 5029), ("Error", 5030), ("Operational", 5031)];
    /// Data types: (the type, its Default Binary and Default XML encodings).
    pub const RESULT_ID: (u32, u32, u32) = (3021, 5274, 5275);
    pub const JOB_ID: (u32, u32, u32) = (3016, 5008, 5026);
    pub const PART_ID: (u32, u32, u32) = (3004, 5013, 5014);
    pub const CONFIGURATION_ID: (u32, u32, u32) = (3008, 5090, 5091);
    pub const RECIPE_ID_INTERNAL: (u32, u32, u32) = (3013, 5268, 5269);
    pub const RESULT_STATE: u32 = 3009;
    pub const MEAS_ID: (u32, u32, u32) = (3015, 5006, 5007);
    pub const PRODUCT_ID: (u32, u32, u32) = (3003, 5224, 5225);
    pub const RECIPE_ID_EXTERNAL: (u32, u32, u32) = (3002, 5002, 5003);
    pub const PROCESSING_TIMES: (u32, u32, u32) = (3005, 5016, 5017);
    pub const RESULT: (u32, u32, u32) = (3006, 5018, 5019);
    /// `Handle`, a UInt32.
    pub const HANDLE: u32 = 3018;
}

/// A node id in OPC 40100-1's namespace by its URI, resolved where it is encoded.
fn mv_id(id: u32) -> ExpandedNodeId {
    ExpandedNodeId { node_id: NodeId::new(0, id), namespace_uri: MV_NAMESPACE.into(), server_index: 0 }
}

/// An OPC 40100-1 structure: its binary and XML encodings (the derives, named one by one since
/// `ua_encodable` gates XML on the calling crate's features) and its data type and encoding ids.
macro_rules! mv_structure {
    ($(#[$meta:meta])* $name:ident, $ids:expr, { $($body:tt)* }) => {
        $(#[$meta])*
        #[derive(
            Debug,
            Clone,
            PartialEq,
            Default,
            opcua::types::BinaryEncodable,
            opcua::types::BinaryDecodable,
            opcua::types::UaNullable,
            opcua::types::XmlEncodable,
            opcua::types::XmlDecodable,
            opcua::types::XmlType
        )]
        pub struct $name { $($body)* }

        impl opcua::types::ExpandedMessageInfo for $name {
            fn full_type_id(&self) -> ExpandedNodeId {
                mv_id($ids.1)
            }
            fn full_json_type_id(&self) -> ExpandedNodeId {
                // OPC 40100-1 1.0 defines no JSON encoding.
                ExpandedNodeId::null()
            }
            fn full_xml_type_id(&self) -> ExpandedNodeId {
                mv_id($ids.2)
            }
            fn full_data_type_id(&self) -> ExpandedNodeId {
                mv_id($ids.0)
            }
        }
    };
}

mv_structure!(
    /// `ResultIdDataType`: the system's id of a result.
    ResultIdDataType, mv::RESULT_ID, { pub id: UAString }
);
mv_structure!(
    /// `JobIdDataType`: the system's id of the job that made a result.
    JobIdDataType, mv::JOB_ID, { pub id: UAString }
);
/// The structures of an `Id` and an optional `Description`.
macro_rules! described_id {
    ($name:ident, $ids:expr, $doc:literal) => {
        mv_structure!(
            #[doc = $doc]
            $name, $ids, {
                pub id: UAString,
                #[opcua(optional)]
                pub description: Option<LocalizedText>,
            }
        );
    };
}
described_id!(PartIdDataType, mv::PART_ID, "`PartIdDataType`: the part a result is about.");
described_id!(MeasIdDataType, mv::MEAS_ID, "`MeasIdDataType`: the client's id of a measurement.");
described_id!(ProductIdDataType, mv::PRODUCT_ID, "`ProductIdDataType`: the product a job was started for.");
mv_structure!(
    /// `ProcessingTimesDataType`: when the job ran; the durations in milliseconds.
    ProcessingTimesDataType, mv::PROCESSING_TIMES, {
        pub start_time: DateTime,
        pub end_time: DateTime,
        #[opcua(optional)]
        pub acquisition_duration: Option<f64>,
        #[opcua(optional)]
        pub processing_duration: Option<f64>,
    }
);

/// `BinaryIdBaseDataType`'s fields, which `ConfigurationIdDataType` and `RecipeIdInternalDataType`
/// inherit unchanged.
macro_rules! binary_id {
    ($name:ident, $ids:expr, $doc:literal) => {
        mv_structure!(
            #[doc = $doc]
            $name, $ids, {
                pub id: UAString,
                #[opcua(optional)]
                pub version: Option<UAString>,
                #[opcua(optional)]
                pub hash: Option<ByteString>,
                #[opcua(optional)]
                pub hash_algorithm: Option<UAString>,
                #[opcua(optional)]
                pub description: Option<LocalizedText>,
            }
        );
    };
}
binary_id!(
    ConfigurationIdDataType,
    mv::CONFIGURATION_ID,
    "`ConfigurationIdDataType`: the configuration (for crestscan, the station) a result was made at."
);
binary_id!(
    RecipeIdInternalDataType,
    mv::RECIPE_ID_INTERNAL,
    "`RecipeIdInternalDataType`: the recipe (the pipeline options) a result was made with."
);

binary_id!(
    RecipeIdExternalDataType,
    mv::RECIPE_ID_EXTERNAL,
    "`RecipeIdExternalDataType`: the environment's id of a recipe."
);

mv_structure!(
    /// `ResultDataType`: a result as `GetResultById` returns it; crestscan's own fields (verdict,
    /// per-thread summary) are in the ResultReady event and the REST report.
    ResultDataType, mv::RESULT, {
        pub result_id: ResultIdDataType,
        #[opcua(optional)]
        pub has_transferable_data_on_file: Option<bool>,
        pub is_partial: bool,
        #[opcua(optional)]
        pub is_simulated: Option<bool>,
        pub result_state: i32,
        #[opcua(optional)]
        pub meas_id: Option<MeasIdDataType>,
        #[opcua(optional)]
        pub part_id: Option<PartIdDataType>,
        #[opcua(optional)]
        pub external_recipe_id: Option<RecipeIdExternalDataType>,
        pub internal_recipe_id: RecipeIdInternalDataType,
        #[opcua(optional)]
        pub product_id: Option<ProductIdDataType>,
        #[opcua(optional)]
        pub external_configuration_id: Option<ConfigurationIdDataType>,
        pub internal_configuration_id: ConfigurationIdDataType,
        pub job_id: JobIdDataType,
        pub creation_time: DateTime,
        #[opcua(optional)]
        pub processing_times: Option<ProcessingTimesDataType>,
        // ResultContent, the last optional field, is left out: crestscan never sends it, and an
        // absent field is only its unset bit in the mask.
    }
);

/// Decodes the OPC 40100-1 structures a client sends (`GetResultById`'s ResultId); the server's
/// own loaders know only the core's.
struct MvTypeLoader;

impl MvTypeLoader {
    fn decode<T: opcua::types::DynEncodable + opcua::types::BinaryDecodable>(
        stream: &mut dyn std::io::Read,
        ctx: &opcua::types::Context<'_>,
    ) -> Option<opcua::types::EncodingResult<Box<dyn opcua::types::DynEncodable>>> {
        Some(T::decode(stream, ctx).map(|t| Box::new(t) as Box<dyn opcua::types::DynEncodable>))
    }
}

impl opcua::types::TypeLoader for MvTypeLoader {
    fn load_from_xml(
        &self,
        _node_id: &NodeId,
        _stream: &mut opcua::types::xml::XmlStreamReader<&mut dyn std::io::Read>,
        _ctx: &opcua::types::Context<'_>,
        _name: &str,
    ) -> Option<opcua::types::EncodingResult<Box<dyn opcua::types::DynEncodable>>> {
        None
    }

    fn load_from_binary(
        &self,
        node_id: &NodeId,
        stream: &mut dyn std::io::Read,
        ctx: &opcua::types::Context<'_>,
        _length: Option<usize>,
    ) -> Option<opcua::types::EncodingResult<Box<dyn opcua::types::DynEncodable>>> {
        if Some(node_id.namespace) != ctx.namespaces().get_index(MV_NAMESPACE) {
            return None;
        }
        let opcua::types::Identifier::Numeric(encoding) = node_id.identifier else { return None };
        match encoding {
            e if e == mv::RESULT_ID.1 => Self::decode::<ResultIdDataType>(stream, ctx),
            e if e == mv::JOB_ID.1 => Self::decode::<JobIdDataType>(stream, ctx),
            e if e == mv::PART_ID.1 => Self::decode::<PartIdDataType>(stream, ctx),
            e if e == mv::MEAS_ID.1 => Self::decode::<MeasIdDataType>(stream, ctx),
            e if e == mv::PRODUCT_ID.1 => Self::decode::<ProductIdDataType>(stream, ctx),
            e if e == mv::CONFIGURATION_ID.1 => Self::decode::<ConfigurationIdDataType>(stream, ctx),
            e if e == mv::RECIPE_ID_INTERNAL.1 => Self::decode::<RecipeIdInternalDataType>(stream, ctx),
            e if e == mv::RECIPE_ID_EXTERNAL.1 => Self::decode::<RecipeIdExternalDataType>(stream, ctx),
            e if e == mv::PROCESSING_TIMES.1 => Self::decode::<ProcessingTimesDataType>(stream, ctx),
            _ => None,
        }
    }

    fn priority(&self) -> opcua::types::TypeLoaderPriority {
        opcua::types::TypeLoaderPriority::Generated
    }
}

/// OPC 40100-1's ResultReadyEventType: its mandatory fields, and the optional PartId.
#[derive(Event)]
#[opcua(identifier = "i=1024", namespace = "http://opcfoundation.org/UA/MachineVision")]
pub struct MvResultReadyEvent {
    base: BaseEventType,
    own_namespace_index: u16,
    creation_time: DateTime,
    result_id: ExtensionObject,
    job_id: ExtensionObject,
    internal_recipe_id: ExtensionObject,
    internal_configuration_id: ExtensionObject,
    is_partial: bool,
    /// Always [`COMPLETED`].
    result_state: i32,
    part_id: Option<ExtensionObject>,
}

/// A succeeded inspection: OPC 40100-1's ResultReadyEventType with crestscan's fields (the
/// per-thread summary as parallel arrays, index i for the thread `ThreadNumbers[i]`).
#[derive(Event)]
#[opcua(identifier = "s=ThreadResultReadyEventType", namespace = "urn:crestscan:machine-vision")]
pub struct ResultReadyEvent {
    base: MvResultReadyEvent,
    own_namespace_index: u16,
    verdict: String,
    decision: String,
    review_required: bool,
    station: String,
    serial: String,
    connection: String,
    report: String,
    thread_numbers: Vec<i32>,
    thread_mean_heights_mm: Vec<f64>,
    thread_height_uncertainties_mm: Vec<f64>,
    thread_findings: Vec<String>,
    thread_black_crest_lengths_mm: Vec<f64>,
}

impl ResultReadyEvent {
    /// The value of field `name` (one of [`RESULT_FIELDS`]), as an event filter selects it;
    /// `Variant::Empty` for a name the event does not have.
    fn field(&self, name: &str) -> Variant {
        use opcua::nodes::Event as _;
        // The derived events match a field by its name; the namespace is the subscriber's.
        self.get_field(
            &ObjectTypeId::BaseEventType.into(),
            opcua::types::AttributeId::Value,
            &opcua::types::NumericRange::None,
            &[QualifiedName::new(self.own_namespace_index, name)],
        )
    }
}

/// The namespace a node id or browse name is in.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Ns {
    Core,
    Mv,
    Own,
}

/// The ids of the server's two namespaces.
#[derive(Debug, Clone, Copy)]
struct Namespaces {
    mv: u16,
    own: u16,
}

impl Namespaces {
    fn index(&self, ns: Ns) -> u16 {
        match ns {
            Ns::Core => 0,
            Ns::Mv => self.mv,
            Ns::Own => self.own,
        }
    }

    fn id(&self, ns: Ns, id: u32) -> NodeId {
        NodeId::new(self.index(ns), id)
    }

    fn name(&self, ns: Ns, name: &str) -> QualifiedName {
        QualifiedName::new(self.index(ns), name)
    }
}

/// A result's fields: the browse name's namespace and name, the data type (its namespace and
/// number) and whether an array. OPC 40100-1's are declared by its type; crestscan's are
/// properties of `ThreadResultReadyEventType`. A client builds its event filter from them.
const RESULT_FIELDS: [(Ns, &str, Ns, u32, bool); 20] = [
    (Ns::Mv, "ResultId", Ns::Mv, mv::RESULT_ID.0, false),
    (Ns::Mv, "JobId", Ns::Mv, mv::JOB_ID.0, false),
    (Ns::Mv, "PartId", Ns::Mv, mv::PART_ID.0, false),
    (Ns::Mv, "InternalRecipeId", Ns::Mv, mv::RECIPE_ID_INTERNAL.0, false),
    (Ns::Mv, "InternalConfigurationId", Ns::Mv, mv::CONFIGURATION_ID.0, false),
    (Ns::Mv, "CreationTime", Ns::Core, DataTypeId::UtcTime as u32, false),
    (Ns::Mv, "IsPartial", Ns::Core, DataTypeId::Boolean as u32, false),
    (Ns::Mv, "ResultState", Ns::Mv, mv::RESULT_STATE, false),
    (Ns::Own, "Verdict", Ns::Core, DataTypeId::String as u32, false),
    (Ns::Own, "Decision", Ns::Core, DataTypeId::String as u32, false),
    (Ns::Own, "ReviewRequired", Ns::Core, DataTypeId::Boolean as u32, false),
    (Ns::Own, "Station", Ns::Core, DataTypeId::String as u32, false),
    (Ns::Own, "Serial", Ns::Core, DataTypeId::String as u32, false),
    (Ns::Own, "Connection", Ns::Core, DataTypeId::String as u32, false),
    (Ns::Own, "Report", Ns::Core, DataTypeId::String as u32, false),
    (Ns::Own, "ThreadNumbers", Ns::Core, DataTypeId::Int32 as u32, true),
    (Ns::Own, "ThreadMeanHeightsMm", Ns::Core, DataTypeId::Double as u32, true),
    (Ns::Own, "ThreadHeightUncertaintiesMm", Ns::Core, DataTypeId::Double as u32, true),
    (Ns::Own, "ThreadFindings", Ns::Core, DataTypeId::String as u32, true),
    (Ns::Own, "ThreadBlackCrestLengthsMm", Ns::Core, DataTypeId::Double as u32, true),
];

/// Unix milliseconds as OPC UA's time (100 ns ticks since 1601-01-01).
fn ua_time(ms: i64) -> DateTime {
    DateTime::from((ms + 11_644_473_600_000) * 10_000)
}

/// ResultStateDataType's `Completed` (OPC 40100-1, 12.19): the processing state, not the part's
/// acceptance, which is the event's `Decision` and `Verdict`. Only succeeded inspections are
/// announced, so every result held is completed.
pub const COMPLETED: i32 = 1;

/// Sessions as the service's API keys allow: anonymous where keys are off; otherwise a user name
/// token (any name) whose password is a key holding `read`.
struct ApiKeys {
    store: Store,
    required: bool,
}

fn rejected(why: &str) -> UaError {
    UaError::new(StatusCode::BadIdentityTokenRejected, why.to_string())
}

#[async_trait::async_trait]
impl AuthManager for ApiKeys {
    async fn authenticate_anonymous_token(&self, _endpoint: &ServerEndpoint) -> Result<(), UaError> {
        if self.required {
            Err(rejected("this service needs an API key: a user name token with the key as its password"))
        } else {
            Ok(())
        }
    }

    async fn authenticate_username_identity_token(
        &self,
        _endpoint: &ServerEndpoint,
        username: &str,
        password: &Password,
    ) -> Result<UserToken, UaError> {
        let row = match self.store.key_for_token(password.get()).await {
            Ok(Some(row)) => row,
            Ok(None) => return Err(rejected("the API key is not valid (unknown, malformed or revoked)")),
            Err(e) => return Err(UaError::new(StatusCode::BadInternalError, format!("the key store: {e}"))),
        };
        if !auth::allows(&row.scopes(), Scope::Read) {
            return Err(rejected("the API key lacks the read scope"));
        }
        tracing::info!(key = %row.id, user = username, "OPC UA session");
        Ok(UserToken(format!("key:{}", row.id)))
    }

    fn user_token_policies(&self, endpoint: &ServerEndpoint) -> Vec<UserTokenPolicy> {
        let mut policies = Vec::with_capacity(2);
        if !self.required {
            policies.push(UserTokenPolicy {
                // The policy id the server checks anonymous tokens against (not exported).
                policy_id: UAString::from("anonymous"),
                token_type: UserTokenType::Anonymous,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: UAString::null(),
            });
        }
        // On an unencrypted channel the password (an API key) is still encrypted with the
        // server's certificate (Part 4, 7.41: the token policy's own security policy).
        let password_policy = endpoint.password_security_policy();
        policies.push(UserTokenPolicy {
            policy_id: user_pass_security_policy_id(endpoint),
            token_type: UserTokenType::UserName,
            issued_token_type: UAString::null(),
            issuer_endpoint_url: UAString::null(),
            security_policy_uri: if endpoint.security_policy() == SecurityPolicy::None {
                UAString::from(password_policy.to_uri())
            } else {
                UAString::null()
            },
        });
        policies
    }
}

/// Node ids of what changes while the server runs.
struct Nodes {
    ns: Namespaces,
    vision_system: NodeId,
    current_state: NodeId,
    current_state_id: NodeId,
    error_reason: NodeId,
    execution_state: NodeId,
    queued: NodeId,
    running: NodeId,
    configurations: NodeId,
    get_result_by_id: NodeId,
    get_result_list_filtered: NodeId,
}

impl Nodes {
    fn id(&self, path: &str) -> NodeId {
        NodeId::new(self.ns.own, path.to_string())
    }
}

/// The server, bound and built, not yet serving.
pub struct OpcUaServer {
    server: Server,
    handle: ServerHandle,
    listener: TcpListener,
    manager: Arc<SimpleNodeManager>,
    nodes: Nodes,
    held: Arc<Held>,
    url: String,
}

impl OpcUaServer {
    /// Binds the endpoint and builds the address space; the error says what failed.
    pub async fn bind(settings: &Settings, store: &Store, url: &str) -> Result<OpcUaServer, String> {
        let endpoint = Endpoint::parse(url).map_err(|e| format!("opcua_endpoint: {e}"))?;
        let listener = TcpListener::bind((endpoint.host.as_str(), endpoint.port))
            .await
            .map_err(|e| format!("opcua_endpoint: cannot listen on {}:{}: {e}", endpoint.host, endpoint.port))?;
        let port = listener.local_addr().map_err(|e| format!("opcua_endpoint: {e}"))?.port();
        let host = if endpoint.host.contains(':') { format!("[{}]", endpoint.host) } else { endpoint.host.clone() };
        let url = format!("opc.tcp://{host}:{port}/");
        let pki = settings.opcua_pki_dir();
        std::fs::create_dir_all(&pki).map_err(|e| format!("opcua_pki_dir {}: {e}", pki.display()))?;
        let nodeset = NodeSet2Import::new_str("en", MV_NODESET, Vec::new())
            .map_err(|e| format!("OPC UA server: OPC 40100's NodeSet (data/opcua/) does not load: {e}"))?;
        let tokens = [ANONYMOUS_USER_TOKEN_ID.to_string()];
        let version = env!("CARGO_PKG_VERSION");
        let mut builder = ServerBuilder::new()
            .application_name("crestscan")
            .application_uri("urn:crestscan:server")
            .product_uri("urn:crestscan")
            .build_info(BuildInfo {
                product_uri: "urn:crestscan".into(),
                manufacturer_name: "crestscan".into(),
                product_name: "crestscan thread inspection".into(),
                software_version: version.into(),
                build_number: version.into(),
                build_date: DateTime::now(),
            })
            .host(endpoint.host.clone())
            .port(port)
            .discovery_urls(vec![url.clone()])
            .pki_dir(pki)
            .create_sample_keypair(true)
            .certificate_path("own/cert.der")
            .private_key_path("private/private.pem")
            .trust_client_certs(false)
            .with_authenticator(Arc::new(ApiKeys {
                store: store.clone(),
                required: settings.auth == AuthMode::Required,
            }))
            .with_type_loader(Arc::new(MvTypeLoader))
            .with_node_manager(simple_node_manager_imports(vec![Box::new(nodeset)], MV_MANAGER))
            .with_node_manager(simple_node_manager(
                NamespaceMetadata { namespace_uri: NAMESPACE.to_owned(), ..Default::default() },
                OWN_MANAGER,
            ));
        if !settings.opcua_require_encryption {
            let mut none = ServerEndpoint::new_none("/", &tokens);
            none.password_security_policy = Some(SecurityPolicy::Basic256Sha256.to_str().to_string());
            builder = builder.add_endpoint("none", none);
        }
        builder = builder
            .add_endpoint("basic256sha256", ServerEndpoint::new_basic256sha256_sign_encrypt("/", &tokens))
            .add_endpoint(
                "aes256sha256rsapss",
                ServerEndpoint::new(
                    "/",
                    SecurityPolicy::Aes256Sha256RsaPss,
                    MessageSecurityMode::SignAndEncrypt,
                    &tokens,
                ),
            );
        let (server, handle) = builder.build().map_err(|e| format!("OPC UA server: {e}"))?;
        let manager = handle
            .node_managers()
            .get_by_name::<SimpleNodeManager>(OWN_MANAGER)
            .ok_or("OPC UA server: its node manager is missing")?;
        let namespace = |uri: &str| {
            handle.get_namespace_index(uri).ok_or_else(|| format!("OPC UA server: the namespace {uri} is missing"))
        };
        let ns = Namespaces { mv: namespace(MV_NAMESPACE)?, own: namespace(NAMESPACE)? };
        let types = handle
            .node_managers()
            .get_by_name::<SimpleNodeManager>(MV_MANAGER)
            .ok_or("OPC UA server: the companion specification's node manager is missing")?;
        {
            let type_tree = handle.type_tree().read();
            let address_space = types.address_space();
            let mut space = address_space.write();
            set_default_encodings(&mut space, &*type_tree);
        }
        let nodes = {
            let address_space = manager.address_space();
            let mut space = address_space.write();
            build_address_space(&mut space, ns)
        };
        let held = Arc::new(Held::default());
        let (by_id, filtered) = (held.clone(), held.clone());
        manager.inner().add_method_callback(nodes.get_result_by_id.clone(), move |args| get_result_by_id(&by_id, args));
        manager.inner().add_method_callback(nodes.get_result_list_filtered.clone(), move |args| {
            get_result_list_filtered(&filtered, args)
        });
        Ok(OpcUaServer { server, handle, listener, manager, nodes, held, url })
    }

    /// The endpoint's URL, with the port taken.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// Serves until `stop`, following the events and the store's state.
    pub async fn run(self, store: Store, mut stop: watch::Receiver<bool>) {
        let OpcUaServer { server, handle, listener, manager, nodes, held, url } = self;
        tracing::info!(%url, "OPC UA server listening");
        let serving = tokio::spawn(server.run_with(listener));
        let mut follower =
            Follower { store, handle: handle.clone(), manager, nodes, held, cursor: None, checked: None };
        let mut tick = tokio::time::interval(POLL);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = tick.tick() => follower.step().await,
                _ = async { let _ = stop.wait_for(|s| *s).await; } => break,
            }
        }
        follower.set_state("Halted", "");
        // A moment for subscribers to read the last state before the sessions close.
        tokio::time::sleep(Duration::from_millis(300)).await;
        handle.cancel();
        match tokio::time::timeout(Duration::from_secs(3), serving).await {
            Ok(Ok(Err(e))) => tracing::warn!(error = %e, "OPC UA server stopped with an error"),
            Err(_) => tracing::warn!("OPC UA server did not stop within 3 s"),
            _ => {}
        }
    }
}

/// Gives each imported structure's definition its default (binary) encoding's id, which the
/// NodeSet import leaves null when the file's namespace index differs from the server's
/// (async-opcua 0.19 matches the encodings by the file's node id text). Generic clients build their
/// decoders from these definitions: asyncua's `load_data_type_definitions` registers each
/// structure under its `DefaultEncodingId`.
fn set_default_encodings(space: &mut AddressSpace, type_tree: &dyn opcua::nodes::TypeTree) {
    use opcua::nodes::NodeType;
    use opcua::types::{BrowseDirection, DataTypeDefinition, ReferenceTypeId};
    let mut parents = vec![NodeId::from(DataTypeId::Structure)];
    while let Some(parent) = parents.pop() {
        let children: Vec<NodeId> = space
            .find_references(&parent, Some((ReferenceTypeId::HasSubtype, false)), type_tree, BrowseDirection::Forward)
            .map(|r| r.target_node.clone())
            .collect();
        for child in children {
            let binary = space
                .find_references(
                    &child,
                    Some((ReferenceTypeId::HasEncoding, false)),
                    type_tree,
                    BrowseDirection::Forward,
                )
                .map(|r| r.target_node.clone())
                .find(|e| {
                    space.find_node(e).is_some_and(|n| n.as_node().browse_name().name.as_ref() == "Default Binary")
                });
            if let (Some(binary), Some(NodeType::DataType(t))) = (binary, space.find_node_mut(&child))
                && let Some(DataTypeDefinition::Structure(mut definition)) = t.data_type_definition().cloned()
                && definition.default_encoding_id.is_null()
            {
                definition.default_encoding_id = binary;
                t.set_data_type_definition(Some(DataTypeDefinition::Structure(definition)));
            }
            parents.push(child);
        }
    }
}

/// The type and instance nodes (module docs).
fn build_address_space(space: &mut AddressSpace, ns: Namespaces) -> Nodes {
    let id = |path: &str| NodeId::new(ns.own, path.to_string());
    let event_type = ResultReadyEvent::event_type_id_from_index(ns.own);
    ObjectTypeBuilder::new(&event_type, ns.name(Ns::Own, "ThreadResultReadyEventType"), "ThreadResultReadyEventType")
        .is_abstract(false)
        .subtype_of(ns.id(Ns::Mv, mv::RESULT_READY_EVENT_TYPE))
        .description("A succeeded inspection's result, with its verdict and per-thread summary")
        .insert(space);
    for (_, name, type_ns, data_type, array) in RESULT_FIELDS.iter().filter(|f| f.0 == Ns::Own) {
        let mut field =
            VariableBuilder::new(&id(&format!("ThreadResultReadyEventType/{name}")), ns.name(Ns::Own, name), *name)
                .property_of(event_type.clone())
                .data_type(ns.id(*type_ns, *data_type))
                .has_type_definition(VariableTypeId::PropertyType)
                .has_modelling_rule(ObjectId::ModellingRule_Mandatory);
        if *array {
            field = field.value_rank(1);
        }
        field.insert(space);
    }

    let system = id("VisionSystem");
    ObjectBuilder::new(&system, ns.name(Ns::Own, "VisionSystem"), "crestscan VisionSystem")
        .description("crestscan's thread inspection (OPC 40100-1, Machine Vision)")
        .event_notifier(EventNotifier::SUBSCRIBE_TO_EVENTS)
        .organized_by(ObjectId::ObjectsFolder)
        .has_type_definition(ns.id(Ns::Mv, mv::VISION_SYSTEM_TYPE))
        .insert(space);
    // A child's id is its path below the VisionSystem ("RecipeManagement/Recipes/default").
    let child = |parent: &NodeId, name: &QualifiedName| match &parent.identifier {
        opcua::types::Identifier::String(path) if *parent != system => id(&format!("{path}/{}", name.name)),
        _ => id(name.name.as_ref()),
    };
    let object = |space: &mut AddressSpace, parent: &NodeId, name: QualifiedName, type_id: NodeId| {
        let node = child(parent, &name);
        let display = name.name.to_string();
        ObjectBuilder::new(&node, name, display)
            .component_of(parent.clone())
            .has_type_definition(type_id)
            .insert(space);
        node
    };
    let variable =
        |space: &mut AddressSpace, parent: &NodeId, name: QualifiedName, value: Variant, data_type: DataTypeId| {
            let node = child(parent, &name);
            let display = name.name.to_string();
            VariableBuilder::new(&node, name, display)
                .component_of(parent.clone())
                .data_type(data_type)
                .has_type_definition(VariableTypeId::BaseDataVariableType)
                .value(value)
                .insert(space);
            node
        };
    let mv_name = |name: &str| ns.name(Ns::Mv, name);
    let own_name = |name: &str| ns.name(Ns::Own, name);
    let mv_type = |number: u32| ns.id(Ns::Mv, number);
    let base_object = || NodeId::from(ObjectTypeId::BaseObjectType);

    let machine = object(space, &system, mv_name("VisionStateMachine"), mv_type(mv::VISION_STATE_MACHINE_TYPE));
    // FiniteStateMachineType's CurrentState, with the state node's id as its Id property.
    let current_state = id("VisionStateMachine/CurrentState");
    VariableBuilder::new(&current_state, QualifiedName::new(0, "CurrentState"), "CurrentState")
        .component_of(machine.clone())
        .data_type(DataTypeId::LocalizedText)
        .has_type_definition(VariableTypeId::FiniteStateVariableType)
        .value(LocalizedText::from("Preoperational"))
        .insert(space);
    let current_state_id = id("VisionStateMachine/CurrentState/Id");
    VariableBuilder::new(&current_state_id, QualifiedName::new(0, "Id"), "Id")
        .property_of(current_state.clone())
        .data_type(DataTypeId::NodeId)
        .has_type_definition(VariableTypeId::PropertyType)
        .value(state_node(ns, "Preoperational"))
        .insert(space);
    let error_reason = variable(space, &machine, own_name("ErrorReason"), "".into(), DataTypeId::String);
    let ready = LocalizedText::from("Ready").into();
    let execution_state = variable(space, &machine, own_name("ExecutionState"), ready, DataTypeId::LocalizedText);
    let queued = variable(space, &machine, own_name("InspectionsQueued"), 0i64.into(), DataTypeId::Int64);
    let running = variable(space, &machine, own_name("InspectionsRunning"), 0i64.into(), DataTypeId::Int64);

    let recipe_manager = object(space, &system, mv_name("RecipeManagement"), mv_type(mv::RECIPE_MANAGEMENT_TYPE));
    let recipes = object(space, &recipe_manager, mv_name("Recipes"), mv_type(mv::RECIPE_FOLDER_TYPE));
    let default = object(space, &recipes, own_name("default"), base_object());
    variable(space, &default, own_name("ExternalId"), "default".into(), DataTypeId::String);
    let options = serde_json::to_string(&crate::pipeline::PipelineOptions::default()).unwrap_or_default();
    variable(space, &default, own_name("Content"), options.into(), DataTypeId::String);

    let configuration_manager =
        object(space, &system, mv_name("ConfigurationManagement"), mv_type(mv::CONFIGURATION_MANAGEMENT_TYPE));
    let configurations =
        object(space, &configuration_manager, mv_name("Configurations"), mv_type(mv::CONFIGURATION_FOLDER_TYPE));

    let results = object(space, &system, mv_name("ResultManagement"), mv_type(mv::RESULT_MANAGEMENT_TYPE));
    let not_held = format!("0, or {RESULT_NOT_HELD}: not among the last {RECENT_RESULTS} results announced");
    // ResultManagementType's GetResultById and GetResultListFiltered (its other methods are not
    // offered: module docs).
    let method = |space: &mut AddressSpace, name: &str, inputs: &[opcua::types::Argument], outputs: &[_]| {
        let node = child(&results, &mv_name(name));
        let arguments = |kind: &str| NodeId::new(ns.own, format!("ResultManagement/{name}/{kind}"));
        opcua::server::address_space::MethodBuilder::new(&node, mv_name(name), name)
            .component_of(results.clone())
            .executable(true)
            .user_executable(true)
            .input_args(space, &arguments("InputArguments"), inputs)
            .output_args(space, &arguments("OutputArguments"), outputs)
            .insert(space);
        node
    };
    let argument = |name: &str, data_type: NodeId, description: &str| opcua::types::Argument {
        name: name.into(),
        data_type,
        value_rank: -1,
        array_dimensions: None,
        description: description.into(),
    };
    let get_result_by_id = method(
        space,
        "GetResultById",
        &[
            argument("ResultId", mv_type(mv::RESULT_ID.0), "the result's id (the inspection's)"),
            argument("Timeout", DataTypeId::Int32.into(), "not used: a result is held or it is not"),
        ],
        &[
            argument("ResultHandle", mv_type(mv::HANDLE), "unique in this server; nothing to release"),
            argument("Result", mv_type(mv::RESULT.0), "the result, if held"),
            argument("Error", DataTypeId::Int32.into(), &not_held),
        ],
    );
    let filter = |name: &str, data_type: NodeId| argument(name, data_type, "a null or empty id filters nothing");
    let get_result_list_filtered = method(
        space,
        "GetResultListFiltered",
        &[
            argument("ResultState", mv_type(mv::RESULT_STATE), "0 filters nothing"),
            filter("MeasId", mv_type(mv::MEAS_ID.0)),
            filter("PartId", mv_type(mv::PART_ID.0)),
            filter("ExternalRecipeId", mv_type(mv::RECIPE_ID_EXTERNAL.0)),
            filter("InternalRecipeId", mv_type(mv::RECIPE_ID_INTERNAL.0)),
            filter("ExternalConfigurationId", mv_type(mv::CONFIGURATION_ID.0)),
            filter("InternalConfigurationId", mv_type(mv::CONFIGURATION_ID.0)),
            filter("ProductId", mv_type(mv::PRODUCT_ID.0)),
            filter("JobId", mv_type(mv::JOB_ID.0)),
            argument("MaxResults", DataTypeId::UInt32.into(), "0: no limit"),
            argument("StartIndex", DataTypeId::UInt32.into(), "0, then multiples of MaxResults"),
            argument("Timeout", DataTypeId::Int32.into(), "not used"),
        ],
        &[
            argument("IsComplete", DataTypeId::Boolean.into(), "the list reaches the last match"),
            argument("ResultCount", DataTypeId::UInt32.into(), "the list's length"),
            argument("ResultHandle", mv_type(mv::HANDLE), "unique in this server; nothing to release"),
            opcua::types::Argument {
                value_rank: 1,
                ..argument("ResultList", mv_type(mv::RESULT.0), "the matches, in the order announced")
            },
            argument("Error", DataTypeId::Int32.into(), "0"),
        ],
    );
    let last_result = object(space, &results, own_name("LastResult"), base_object());
    for (name_ns, name, type_ns, data_type, array) in RESULT_FIELDS {
        let value = match (array, type_ns, data_type) {
            (true, _, t) if t == DataTypeId::Int32 as u32 => Variant::from(Vec::<i32>::new()),
            (true, _, t) if t == DataTypeId::Double as u32 => Variant::from(Vec::<f64>::new()),
            (true, _, _) => Variant::from(Vec::<String>::new()),
            (false, Ns::Core, t) if t == DataTypeId::Boolean as u32 => false.into(),
            (false, Ns::Core, t) if t == DataTypeId::String as u32 => "".into(),
            // No result yet: the structures and the time are null.
            _ => Variant::Empty,
        };
        let mut field =
            VariableBuilder::new(&id(&format!("ResultManagement/LastResult/{name}")), ns.name(name_ns, name), name)
                .component_of(last_result.clone())
                .data_type(ns.id(type_ns, data_type))
                .has_type_definition(VariableTypeId::BaseDataVariableType)
                .value(value);
        if array {
            field = field.value_rank(1);
        }
        field.insert(space);
    }
    Nodes {
        ns,
        vision_system: system,
        current_state,
        current_state_id,
        error_reason,
        execution_state,
        queued,
        running,
        configurations,
        get_result_by_id,
        get_result_list_filtered,
    }
}

/// The argument `index` of a method call as the structure `T`: `Ok(None)` where the client sent a
/// null (an empty filter).
fn structure_argument<T: Send + Sync + 'static>(args: &[Variant], index: usize) -> Result<Option<&T>, StatusCode> {
    match args.get(index) {
        Some(Variant::ExtensionObject(o)) if o.is_null() => Ok(None),
        Some(Variant::ExtensionObject(o)) => o.inner_as::<T>().map(Some).ok_or(StatusCode::BadTypeMismatch),
        Some(Variant::Empty) => Ok(None),
        Some(_) => Err(StatusCode::BadTypeMismatch),
        None => Err(StatusCode::BadArgumentsMissing),
    }
}

/// Refuses a call with other than `count` arguments.
fn argument_count(args: &[Variant], count: usize) -> Result<(), StatusCode> {
    match args.len().cmp(&count) {
        std::cmp::Ordering::Less => Err(StatusCode::BadArgumentsMissing),
        std::cmp::Ordering::Greater => Err(StatusCode::BadTooManyArguments),
        std::cmp::Ordering::Equal => Ok(()),
    }
}

/// `GetResultById(ResultId, Timeout) -> (ResultHandle, Result, Error)` over the results held.
fn get_result_by_id(held: &Held, args: &[Variant]) -> Result<Vec<Variant>, StatusCode> {
    argument_count(args, 2)?;
    let id = structure_argument::<ResultIdDataType>(args, 0)?.ok_or(StatusCode::BadInvalidArgument)?;
    if !matches!(args[1], Variant::Int32(_)) {
        return Err(StatusCode::BadTypeMismatch);
    }
    let found = held.results().iter().rev().find(|r| r.result_id == *id).cloned();
    let (result, error) = match found {
        Some(result) => (Variant::from(ExtensionObject::from_message(result)), 0),
        None => (Variant::ExtensionObject(ExtensionObject::null()), RESULT_NOT_HELD),
    };
    Ok(vec![held.handle(), result, Variant::Int32(error)])
}

/// `GetResultListFiltered(ResultState, MeasId, PartId, ExternalRecipeId, InternalRecipeId,
/// ExternalConfigurationId, InternalConfigurationId, ProductId, JobId, MaxResults, StartIndex,
/// Timeout) -> (IsComplete, ResultCount, ResultHandle, ResultList, Error)` over the results held,
/// in the order announced. A state of 0 and a null or empty id filter nothing; an id matches by its
/// `Id`. A filter on an id crestscan never sets (MeasId, ProductId, the external ids) matches no
/// result. `ResultCount` is the length of `ResultList`; `IsComplete` says it reaches the last match.
fn get_result_list_filtered(held: &Held, args: &[Variant]) -> Result<Vec<Variant>, StatusCode> {
    argument_count(args, 12)?;
    let Variant::Int32(state) = args[0] else { return Err(StatusCode::BadTypeMismatch) };
    // Each id filter as its `Id`, None where empty.
    fn id_of(id: &UAString) -> Option<&str> {
        id.value().as_deref().filter(|id| !id.is_empty())
    }
    let meas = structure_argument::<MeasIdDataType>(args, 1)?.and_then(|i| id_of(&i.id));
    let part = structure_argument::<PartIdDataType>(args, 2)?.and_then(|i| id_of(&i.id));
    let external_recipe = structure_argument::<RecipeIdExternalDataType>(args, 3)?.and_then(|i| id_of(&i.id));
    let recipe = structure_argument::<RecipeIdInternalDataType>(args, 4)?.and_then(|i| id_of(&i.id));
    let external_configuration = structure_argument::<ConfigurationIdDataType>(args, 5)?.and_then(|i| id_of(&i.id));
    let configuration = structure_argument::<ConfigurationIdDataType>(args, 6)?.and_then(|i| id_of(&i.id));
    let product = structure_argument::<ProductIdDataType>(args, 7)?.and_then(|i| id_of(&i.id));
    let job = structure_argument::<JobIdDataType>(args, 8)?.and_then(|i| id_of(&i.id));
    let (Variant::UInt32(max_results), Variant::UInt32(start), Variant::Int32(_)) = (&args[9], &args[10], &args[11])
    else {
        return Err(StatusCode::BadTypeMismatch);
    };
    let unset = meas.is_some() || external_recipe.is_some() || external_configuration.is_some() || product.is_some();
    let matches = |r: &&ResultDataType| {
        !unset
            && (state == 0 || r.result_state == state)
            && part.is_none_or(|p| r.part_id.as_ref().and_then(|i| id_of(&i.id)) == Some(p))
            && recipe.is_none_or(|p| id_of(&r.internal_recipe_id.id) == Some(p))
            && configuration.is_none_or(|p| r.internal_configuration_id.id.as_ref() == p)
            && job.is_none_or(|p| id_of(&r.job_id.id) == Some(p))
    };
    let results = held.results();
    let matching: Vec<&ResultDataType> = results.iter().filter(matches).collect();
    let limit = if *max_results == 0 { usize::MAX } else { *max_results as usize };
    let page: Vec<ExtensionObject> = matching
        .iter()
        .skip(*start as usize)
        .take(limit)
        .map(|r| ExtensionObject::from_message((*r).clone()))
        .collect();
    let complete = (*start as usize).saturating_add(page.len()) >= matching.len();
    Ok(vec![
        Variant::Boolean(complete),
        Variant::UInt32(page.len() as u32),
        held.handle(),
        Variant::from(page),
        Variant::Int32(0),
    ])
}

/// The node of VisionStateMachineType's state `name` (Preoperational if the name is not one).
fn state_node(ns: Namespaces, name: &str) -> NodeId {
    let number = mv::STATES.iter().find(|(state, _)| *state == name).unwrap_or(&mv::STATES[0]).1;
    ns.id(Ns::Mv, number)
}

/// Follows the events table and the store's state into the address space.
struct Follower {
    store: Store,
    handle: ServerHandle,
    manager: Arc<SimpleNodeManager>,
    nodes: Nodes,
    held: Arc<Held>,
    /// The last event seen; None until the first step reads where the table ends.
    cursor: Option<i64>,
    /// When the store was last checked, and whether it was healthy then.
    checked: Option<(std::time::Instant, bool)>,
}

impl Follower {
    fn set(&self, id: &NodeId, value: impl Into<Variant>) {
        let value = DataValue::new_now(value.into());
        if let Err(e) = self.manager.set_value(self.handle.subscriptions(), id, None, value) {
            tracing::warn!(node = %id, status = %e, "OPC UA: a value could not be set");
        }
    }

    fn set_state(&self, state: &str, reason: &str) {
        self.set(&self.nodes.current_state, LocalizedText::from(state));
        self.set(&self.nodes.current_state_id, state_node(self.nodes.ns, state));
        self.set(&self.nodes.error_reason, reason);
    }

    async fn step(&mut self) {
        if self.checked.is_none_or(|(at, _)| at.elapsed() >= HEALTH) {
            self.checked = Some((std::time::Instant::now(), self.check_health().await));
        }
        if self.checked.is_some_and(|(_, healthy)| !healthy) {
            return;
        }
        if let Ok((queued, running)) = self.store.queue_depth().await {
            self.set(&self.nodes.queued, queued);
            self.set(&self.nodes.running, running);
            let execution = if queued + running > 0 { "Executing" } else { "Ready" };
            self.set(&self.nodes.execution_state, LocalizedText::from(execution));
        }
        if let Err(e) = self.follow().await {
            // Read again at the next poll; a store that stays away turns the state to Error.
            tracing::warn!(error = %e, "OPC UA: the events could not be read; tried again");
        }
    }

    /// Operational when the store reads and takes a write, else Error with the reason.
    async fn check_health(&self) -> bool {
        let healthy = self.store.database_ready().await;
        match &healthy {
            Ok(()) => self.set_state("Operational", ""),
            Err(reason) => {
                tracing::warn!(%reason, "OPC UA: the vision system is in Error");
                self.set_state("Error", reason);
            }
        }
        healthy.is_ok()
    }

    /// Applies the events after the cursor: stations' statuses and succeeded inspections' results.
    async fn follow(&mut self) -> Result<(), StoreError> {
        let mut cursor = match self.cursor {
            Some(cursor) => cursor,
            None => {
                // Stations as they are now, then only what changes: the table's end is read
                // first, so a station changed in between is applied twice, never missed.
                let end = self.store.count("SELECT COALESCE(MAX(seq), 0) FROM events").await?;
                for s in self.store.stations().await? {
                    self.station(&s.name, &s.status, s.status_reason.as_deref().unwrap_or(""));
                }
                self.cursor = Some(end);
                end
            }
        };
        let events = self.store.events_after(cursor, BATCH).await?;
        for event in events {
            let done = match event.subject_kind.as_str() {
                "inspection" if event.status == "succeeded" => self.result(&event.subject, event.seq).await,
                "inspection" => Ok(()),
                _ => {
                    let reason = match self.store.station(&event.subject).await {
                        Ok(s) => s.status_reason.unwrap_or_default(),
                        Err(StoreError::NotFound) => String::new(),
                        Err(e) => {
                            tracing::warn!(error = %e, "OPC UA: a station could not be read; tried again");
                            break;
                        }
                    };
                    self.station(&event.subject, &event.status, &reason);
                    Ok(())
                }
            };
            if let Err(e) = done {
                tracing::warn!(error = %e, "OPC UA: a result could not be read; tried again");
                break;
            }
            cursor = event.seq;
        }
        self.cursor = Some(cursor);
        Ok(())
    }

    /// A station's configuration node, added the first time it is seen.
    fn station(&self, name: &str, status: &str, reason: &str) {
        let object = self.nodes.id(&format!("ConfigurationManagement/Configurations/{name}"));
        let status_id = self.nodes.id(&format!("ConfigurationManagement/Configurations/{name}/Status"));
        let reason_id = self.nodes.id(&format!("ConfigurationManagement/Configurations/{name}/StatusReason"));
        {
            let address_space = self.manager.address_space();
            let mut space = address_space.write();
            if !space.node_exists(&object) {
                ObjectBuilder::new(&object, self.nodes.ns.name(Ns::Own, name), name)
                    .component_of(self.nodes.configurations.clone())
                    .has_type_definition(ObjectTypeId::BaseObjectType)
                    .insert(&mut *space);
                for (id, field) in [(&status_id, "Status"), (&reason_id, "StatusReason")] {
                    VariableBuilder::new(id, self.nodes.ns.name(Ns::Own, field), field)
                        .component_of(object.clone())
                        .data_type(DataTypeId::String)
                        .has_type_definition(VariableTypeId::BaseDataVariableType)
                        .value("")
                        .insert(&mut *space);
                }
            }
        }
        self.set(&status_id, status);
        self.set(&reason_id, reason);
    }

    /// Announces a succeeded inspection: LastResult and a ResultReadyEvent.
    async fn result(&self, id: &str, seq: i64) -> Result<(), StoreError> {
        let row = match self.store.inspection(id).await {
            Ok(row) => row,
            Err(StoreError::NotFound) => return Ok(()),
            Err(e) => return Err(e),
        };
        let (threads, _) = self.store.threads(id).await?;
        let event = result_event(&row, &threads, self.nodes.ns, self.nodes.vision_system.clone());
        self.held.hold(result_data(&row));
        // LastResult reads each field from the event as a subscriber's select clause would, so
        // that the two cannot differ (a unit test checks every field is found).
        for (_, name, _, _, _) in RESULT_FIELDS {
            self.set(&self.nodes.id(&format!("ResultManagement/LastResult/{name}")), event.field(name));
        }
        self.handle
            .subscriptions()
            .notify_events([(&event as &dyn opcua::nodes::Event, &self.nodes.vision_system)].into_iter());
        tracing::debug!(inspection = id, seq, "OPC UA: result announced");
        Ok(())
    }
}

/// The recipe an inspection ran with: `default`, or `custom` where its pipeline options differ
/// from the defaults; the hash (SHA-256 of the options as JSON) tells one custom recipe from
/// another, and equals the default recipe's `Content`'s hash for `default`.
fn recipe_id(options_json: &str) -> RecipeIdInternalDataType {
    let pipeline = serde_json::from_str::<crate::service::queue::JobOptions>(options_json).ok().map(|o| o.pipeline);
    let default = pipeline.as_ref() == Some(&crate::pipeline::PipelineOptions::default());
    let content = pipeline.and_then(|p| serde_json::to_string(&p).ok()).unwrap_or_else(|| options_json.to_string());
    RecipeIdInternalDataType {
        id: if default { "default" } else { "custom" }.into(),
        hash: Some(ByteString::from(Sha256::digest(content.as_bytes()).to_vec())),
        hash_algorithm: Some("SHA-256".into()),
        ..Default::default()
    }
}

/// A succeeded inspection as OPC 40100-1's result.
fn result_data(row: &InspectionRow) -> ResultDataType {
    let id = UAString::from(row.id.as_str());
    let finished_ms = row.finished_at.unwrap_or(row.updated_at);
    ResultDataType {
        result_id: ResultIdDataType { id: id.clone() },
        is_partial: false,
        result_state: COMPLETED,
        part_id: row
            .serial
            .as_deref()
            .filter(|s| !s.is_empty())
            .map(|s| PartIdDataType { id: s.into(), description: None }),
        internal_recipe_id: recipe_id(&row.options_json),
        // No station: the station design the simulator defines ("" as the id).
        internal_configuration_id: ConfigurationIdDataType {
            id: row.station.as_deref().unwrap_or("").into(),
            ..Default::default()
        },
        // The inspection is the job that made the result.
        job_id: JobIdDataType { id },
        creation_time: ua_time(finished_ms),
        processing_times: row.started_at.map(|started_ms| ProcessingTimesDataType {
            start_time: ua_time(started_ms),
            end_time: ua_time(finished_ms),
            acquisition_duration: None,
            processing_duration: Some((finished_ms - started_ms) as f64),
        }),
        ..Default::default()
    }
}

/// The ResultReady event of a succeeded inspection and its threads.
fn result_event(
    row: &InspectionRow,
    threads: &[crate::service::store::ThreadRow],
    ns: Namespaces,
    source: NodeId,
) -> ResultReadyEvent {
    let id = row.id.as_str();
    let event_type = ResultReadyEvent::event_type_id_from_index(ns.own);
    let verdict = row.verdict.clone().unwrap_or_default();
    let decision = row.decision.clone().unwrap_or_default();
    let message = format!("inspection {id}: {verdict}, {decision}");
    let time = ua_time(row.finished_at.unwrap_or(row.updated_at));
    let base = BaseEventType::new(event_type, ByteString::from(id.as_bytes().to_vec()), message, time)
        .set_source_node(source)
        .set_source_name(UAString::from("VisionSystem"))
        .set_severity(if row.review_required == Some(true) { 500 } else { 100 });
    let data = result_data(row);
    let mv = MvResultReadyEvent {
        base,
        own_namespace_index: ns.mv,
        creation_time: data.creation_time,
        result_id: ExtensionObject::from_message(data.result_id),
        job_id: ExtensionObject::from_message(data.job_id),
        internal_recipe_id: ExtensionObject::from_message(data.internal_recipe_id),
        internal_configuration_id: ExtensionObject::from_message(data.internal_configuration_id),
        is_partial: data.is_partial,
        result_state: data.result_state,
        part_id: data.part_id.map(ExtensionObject::from_message),
    };
    ResultReadyEvent {
        base: mv,
        own_namespace_index: ns.own,
        verdict,
        decision,
        review_required: row.review_required.unwrap_or(false),
        station: row.station.clone().unwrap_or_default(),
        serial: row.serial.clone().unwrap_or_default(),
        connection: row.connection.clone().unwrap_or_default(),
        report: format!("/v1/inspections/{id}/report"),
        thread_numbers: threads.iter().map(|t| t.thread_index as i32).collect(),
        thread_mean_heights_mm: threads.iter().map(|t| t.mean_height_mm.unwrap_or(f64::NAN)).collect(),
        thread_height_uncertainties_mm: threads
            .iter()
            .map(|t| t.mean_height_uncertainty_mm.unwrap_or(f64::NAN))
            .collect(),
        thread_findings: threads.iter().map(|t| t.height_finding.clone().unwrap_or_default()).collect(),
        thread_black_crest_lengths_mm: threads.iter().map(|t| t.black_crest_length_mm).collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use opcua::types::{BinaryEncodable, Context, ContextOwned, DecodingOptions, NamespaceMap, TypeLoaderCollection};

    const NS: Namespaces = Namespaces { mv: 2, own: 3 };

    fn row(decision: &str, serial: Option<&str>, options: &crate::service::queue::JobOptions) -> InspectionRow {
        serde_json::from_value(serde_json::json!({
            "id": "0190-id", "status": "succeeded", "upload_sha256": "ab", "serial": serial,
            "connection": "buttress", "client_reference": null,
            "options_json": serde_json::to_string(options).unwrap(), "verdict": "accept",
            "review_required": true, "decision": decision, "created_at": 1, "updated_at": 2,
            "started_at": 1, "finished_at": 1_765_000_000_000i64, "progress_stage": null,
            "progress_fraction": null, "attempts": 1, "max_attempts": 3, "cancel_requested": false,
            "error_json": null, "request_sha256": "cd", "station": "line-3", "size_bytes": 10,
            "views": 1, "frames": 5
        }))
        .unwrap()
    }

    fn thread(index: i64, mean_mm: f64) -> crate::service::store::ThreadRow {
        crate::service::store::ThreadRow {
            thread_index: index,
            crest_z_start_mm: 0.0,
            crest_z_end_mm: 1.0,
            min_height_mm: Some(mean_mm),
            mean_height_mm: Some(mean_mm),
            max_height_mm: Some(mean_mm),
            bins_measured: 360,
            black_crest_length_mm: 0.5 * index as f64,
            black_crest_arcs_json: "[]".into(),
            mean_height_uncertainty_mm: Some(0.004),
            height_finding: Some("conforms".into()),
        }
    }

    fn default_options() -> crate::service::queue::JobOptions {
        crate::service::queue::JobOptions { pipeline: crate::pipeline::PipelineOptions::default(), callback_url: None }
    }

    /// The event's fields as a subscriber's select clause reads them: every name [`RESULT_FIELDS`]
    /// declares (for the type node and LastResult) is found, of the declared type and shape.
    #[test]
    fn every_declared_field_is_the_events_own() {
        let event = result_event(
            &row("conforms", Some("SN-1"), &default_options()),
            &[thread(1, 1.57), thread(2, 1.58)],
            NS,
            NodeId::new(NS.own, "VisionSystem"),
        );
        for (_, name, type_ns, data_type, array) in RESULT_FIELDS {
            let value = event.field(name);
            let expected = match (type_ns, array) {
                (Ns::Mv, false) if data_type == mv::RESULT_STATE => matches!(value, Variant::Int32(_)),
                (Ns::Mv, false) => matches!(value, Variant::ExtensionObject(_)),
                (_, true) => matches!(&value, Variant::Array(a) if a.values.len() == 2),
                (_, false) if data_type == DataTypeId::String as u32 => matches!(value, Variant::String(_)),
                (_, false) if data_type == DataTypeId::Boolean as u32 => matches!(value, Variant::Boolean(_)),
                (_, false) if data_type == DataTypeId::UtcTime as u32 => matches!(value, Variant::DateTime(_)),
                _ => false,
            };
            assert!(expected, "{name}: {value:?}");
        }
        assert_eq!(event.field("ResultState"), Variant::Int32(COMPLETED));
        // The state is the processing's, not the part's: a rejected part's result is completed too.
        let rejected = result_event(&row("does_not_conform", None, &default_options()), &[], NS, NodeId::null());
        assert_eq!(rejected.field("ResultState"), Variant::Int32(COMPLETED));
        assert_eq!(rejected.field("Decision"), Variant::from("does_not_conform"));
        assert_eq!(event.field("ThreadMeanHeightsMm"), Variant::from(vec![1.57, 1.58]));
        assert_eq!(event.field("NoSuchField"), Variant::Empty);
        let Variant::ExtensionObject(id) = event.field("ResultId") else { panic!("ResultId") };
        assert_eq!(id.inner_as::<ResultIdDataType>(), Some(&ResultIdDataType { id: "0190-id".into() }));
        let Variant::ExtensionObject(part) = event.field("PartId") else { panic!("PartId") };
        assert_eq!(part.inner_as::<PartIdDataType>().unwrap().id.as_ref(), "SN-1");
        // Without a serial there is no PartId (the field is optional in OPC 40100-1).
        let anonymous = result_event(&row("conforms", None, &default_options()), &[], NS, NodeId::null());
        assert_eq!(anonymous.field("PartId"), Variant::Empty);
    }

    /// The structures encode as OPC 40100-1's binary encodings: the encoding's node id by the
    /// namespace's index, then the fields, the optional ones behind a mask (Part 6, 5.2.7).
    #[test]
    fn the_structures_encode_as_the_specifications() {
        let mut namespaces = NamespaceMap::new();
        namespaces.add_namespace(MV_NAMESPACE);
        let owned = ContextOwned::new(namespaces, TypeLoaderCollection::new(), DecodingOptions::default());
        let ctx: Context<'_> = owned.context();
        let encode = |object: ExtensionObject| {
            let mut bytes = Vec::new();
            object.encode(&mut bytes, &ctx).unwrap();
            bytes
        };
        let result_id = encode(ExtensionObject::from_message(ResultIdDataType { id: "ab".into() }));
        // NodeId four-byte form (ns 1, 5274), binary body, body length 6, the string "ab".
        let mut expected = vec![0x01, 0x01];
        expected.extend(5274u16.to_le_bytes());
        expected.push(0x01);
        expected.extend(6i32.to_le_bytes());
        expected.extend(2i32.to_le_bytes());
        expected.extend(b"ab");
        assert_eq!(result_id, expected);

        let recipe = recipe_id(&serde_json::to_string(&default_options()).unwrap());
        assert_eq!(recipe.id.as_ref(), "default");
        let recipe = encode(ExtensionObject::from_message(recipe));
        // After the 9-byte header (node id, encoding byte, length): the mask has Hash (bit 1) and
        // HashAlgorithm (bit 2), then Id, the 32-byte hash, "SHA-256".
        assert_eq!(&recipe[..4], &[0x01, 0x01, 0x94, 0x14], "RecipeIdInternalDataType's encoding 5268");
        assert_eq!(u32::from_le_bytes(recipe[9..13].try_into().unwrap()), 0b110);
        assert_eq!(recipe.len(), 9 + 4 + (4 + 7) + (4 + 32) + (4 + 7));

        let mut custom = default_options();
        custom.pipeline.cell_px *= 2.0;
        assert_eq!(recipe_id(&serde_json::to_string(&custom).unwrap()).id.as_ref(), "custom");
        // The callback is not part of the recipe.
        let mut called = default_options();
        called.callback_url = Some("https://mes.example/hook".into());
        let (plain, hooked) = (
            recipe_id(&serde_json::to_string(&default_options()).unwrap()),
            recipe_id(&serde_json::to_string(&called).unwrap()),
        );
        assert_eq!(plain, hooked);
    }

    /// GetResultById answers from the results held, newest first, and refuses arguments of the
    /// wrong number or type with the status Part 4 names.
    #[test]
    fn get_result_by_id_answers_from_the_results_held() {
        let held = Held::default();
        let mut first = result_data(&row("conforms", Some("SN-1"), &default_options()));
        first.result_state = -7;
        held.results().push_back(first);
        held.results().push_back(result_data(&row("conforms", Some("SN-1"), &default_options())));
        let ask = |id: &str| {
            get_result_by_id(
                &held,
                &[ExtensionObject::from_message(ResultIdDataType { id: id.into() }).into(), Variant::Int32(0)],
            )
        };
        let answer = ask("0190-id").unwrap();
        assert_eq!(answer[2], Variant::Int32(0));
        let Variant::ExtensionObject(result) = &answer[1] else { panic!("{answer:?}") };
        let result = result.inner_as::<ResultDataType>().unwrap();
        assert_eq!(result.result_state, COMPLETED, "the newest of two with one id");
        assert_eq!(result.part_id.as_ref().unwrap().id.as_ref(), "SN-1");
        assert_eq!(
            result.processing_times.as_ref().unwrap().processing_duration,
            Some((1_765_000_000_000i64 - 1) as f64)
        );

        let missing = ask("other").unwrap();
        assert_eq!(missing[1], Variant::ExtensionObject(ExtensionObject::null()));
        assert_eq!(missing[2], Variant::Int32(RESULT_NOT_HELD));
        // Each answer has its own handle.
        assert!(answer[0] != missing[0] && answer[0] != Variant::UInt32(0), "{answer:?} {missing:?}");

        assert_eq!(get_result_by_id(&held, &[]), Err(StatusCode::BadArgumentsMissing));
        let id = Variant::from(ExtensionObject::from_message(ResultIdDataType { id: "0190-id".into() }));
        assert_eq!(
            get_result_by_id(&held, &[id.clone(), Variant::Int32(0), Variant::Int32(0)]),
            Err(StatusCode::BadTooManyArguments)
        );
        assert_eq!(
            get_result_by_id(&held, &[Variant::from("0190-id"), Variant::Int32(0)]),
            Err(StatusCode::BadTypeMismatch)
        );
        let job = Variant::from(ExtensionObject::from_message(JobIdDataType { id: "0190-id".into() }));
        assert_eq!(get_result_by_id(&held, &[job, Variant::Int32(0)]), Err(StatusCode::BadTypeMismatch));
        assert_eq!(get_result_by_id(&held, &[id, Variant::Double(0.0)]), Err(StatusCode::BadTypeMismatch));
    }

    /// A result announced again is held once, at the back; past the bound the oldest goes.
    #[test]
    fn results_are_held_once_and_bounded() {
        let held = Held::default();
        let result = |i: usize| {
            let mut inspection = row("conforms", None, &default_options());
            inspection.id = format!("id-{i}");
            result_data(&inspection)
        };
        for i in 0..RECENT_RESULTS + 2 {
            held.hold(result(i));
        }
        held.hold(result(5));
        let held = held.results();
        assert_eq!(held.len(), RECENT_RESULTS);
        let ids: Vec<String> = held.iter().map(|r| r.result_id.id.to_string()).collect();
        assert_eq!(ids.iter().filter(|id| *id == "id-5").count(), 1);
        assert_eq!(ids.last().map(String::as_str), Some("id-5"));
        assert!(!ids.contains(&"id-0".to_string()) && !ids.contains(&"id-1".to_string()), "{:?}", &ids[..3]);
    }

    /// GetResultListFiltered filters by state and ids, pages with MaxResults and StartIndex, and
    /// matches nothing on an id crestscan never sets.
    #[test]
    fn get_result_list_filtered_filters_and_pages() {
        let held = Held::default();
        for (i, serial) in ["SN-1", "SN-2", "SN-1", "SN-3", "SN-1"].iter().enumerate() {
            let mut inspection = row("conforms", Some(serial), &default_options());
            inspection.id = format!("id-{i}");
            inspection.station = Some(if i < 3 { "line-3" } else { "line-4" }.into());
            held.results().push_back(result_data(&inspection));
        }
        let object = |o: ExtensionObject| Variant::ExtensionObject(o);
        let none = || Variant::ExtensionObject(ExtensionObject::null());
        let ask =
            |state: i32, part: Option<&str>, configuration: Option<&str>, meas: Option<&str>, max: u32, start: u32| {
                let mut args = vec![Variant::Int32(state)];
                args.push(meas.map_or_else(none, |m| {
                    object(ExtensionObject::from_message(MeasIdDataType { id: m.into(), description: None }))
                }));
                args.push(part.map_or_else(none, |p| {
                    object(ExtensionObject::from_message(PartIdDataType { id: p.into(), description: None }))
                }));
                args.extend([none(), none(), none()]);
                args.push(configuration.map_or_else(none, |c| {
                    object(ExtensionObject::from_message(ConfigurationIdDataType {
                        id: c.into(),
                        ..Default::default()
                    }))
                }));
                args.extend([none(), none(), Variant::UInt32(max), Variant::UInt32(start), Variant::Int32(-1)]);
                let out = get_result_list_filtered(&held, &args).unwrap();
                let Variant::Array(list) = &out[3] else { panic!("{out:?}") };
                let ids: Vec<String> = list
                    .values
                    .iter()
                    .map(|v| match v {
                        Variant::ExtensionObject(o) => o.inner_as::<ResultDataType>().unwrap().result_id.id.to_string(),
                        other => panic!("{other:?}"),
                    })
                    .collect();
                assert_eq!(out[1], Variant::UInt32(ids.len() as u32));
                assert_eq!(out[4], Variant::Int32(0));
                (out[0] == Variant::Boolean(true), ids)
            };
        let all = ask(0, None, None, None, 0, 0);
        assert_eq!(all, (true, vec!["id-0".into(), "id-1".into(), "id-2".into(), "id-3".into(), "id-4".into()]));
        assert_eq!(ask(COMPLETED, None, None, None, 0, 0).1.len(), 5);
        assert_eq!(ask(4, None, None, None, 0, 0), (true, vec![]));
        assert_eq!(ask(0, Some("SN-1"), None, None, 0, 0).1, ["id-0", "id-2", "id-4"]);
        assert_eq!(ask(0, Some("SN-1"), Some("line-3"), None, 0, 0).1, ["id-0", "id-2"]);
        assert_eq!(ask(0, Some(""), Some("line-4"), None, 0, 0).1, ["id-3", "id-4"], "an empty id filters nothing");
        // Pages of two: StartIndex 0, 2, 4.
        assert_eq!(ask(0, None, None, None, 2, 0), (false, vec!["id-0".into(), "id-1".into()]));
        assert_eq!(ask(0, None, None, None, 2, 2), (false, vec!["id-2".into(), "id-3".into()]));
        assert_eq!(ask(0, None, None, None, 2, 4), (true, vec!["id-4".into()]));
        assert_eq!(ask(0, None, None, None, 2, 6), (true, vec![]));
        assert_eq!(ask(0, None, None, Some("M-1"), 0, 0), (true, vec![]), "MeasId is never set");

        assert_eq!(get_result_list_filtered(&held, &[Variant::Int32(0)]), Err(StatusCode::BadArgumentsMissing));
        let mut wrong = vec![Variant::Int32(0)];
        wrong.extend((0..8).map(|_| none()));
        wrong.extend([Variant::Int32(0), Variant::UInt32(0), Variant::Int32(0)]);
        assert_eq!(get_result_list_filtered(&held, &wrong), Err(StatusCode::BadTypeMismatch), "MaxResults is a UInt32");
        wrong[9] = Variant::UInt32(0);
        wrong[2] = object(ExtensionObject::from_message(JobIdDataType { id: "SN-1".into() }));
        assert_eq!(get_result_list_filtered(&held, &wrong), Err(StatusCode::BadTypeMismatch), "PartId's type");
    }

    /// A ResultIdDataType a client sends decodes through the server's loader.
    #[test]
    fn the_loader_decodes_what_a_client_sends() {
        let mut namespaces = NamespaceMap::new();
        namespaces.add_namespace(MV_NAMESPACE);
        let mut loaders = TypeLoaderCollection::new();
        loaders.add(Arc::new(MvTypeLoader));
        let owned = ContextOwned::new(namespaces, loaders, DecodingOptions::default());
        let ctx: Context<'_> = owned.context();
        let sent = ExtensionObject::from_message(ResultIdDataType { id: "0190-id".into() });
        let mut bytes = Vec::new();
        sent.encode(&mut bytes, &ctx).unwrap();
        let back = <ExtensionObject as opcua::types::BinaryDecodable>::decode(&mut bytes.as_slice(), &ctx).unwrap();
        assert_eq!(back.inner_as::<ResultIdDataType>(), Some(&ResultIdDataType { id: "0190-id".into() }));
    }

    /// The compiled-in NodeSet parses, and declares the types and states the server refers to.
    #[test]
    fn the_companion_nodeset_holds_what_the_server_refers_to() {
        let text = MV_NODESET;
        NodeSet2Import::new_str("en", text, Vec::new()).expect("the NodeSet parses");
        assert!(text.contains(&format!("<Uri>{MV_NAMESPACE}</Uri>")));
        let declared = |id: u32, name: &str| {
            let tag = format!("NodeId=\"ns=1;i={id}\" BrowseName=\"1:{name}\"");
            assert!(text.contains(&tag), "{tag}");
        };
        declared(mv::VISION_SYSTEM_TYPE, "VisionSystemType");
        declared(mv::RECIPE_MANAGEMENT_TYPE, "RecipeManagementType");
        declared(mv::CONFIGURATION_MANAGEMENT_TYPE, "ConfigurationManagementType");
        declared(mv::RESULT_MANAGEMENT_TYPE, "ResultManagementType");
        declared(mv::RECIPE_FOLDER_TYPE, "RecipeFolderType");
        declared(mv::CONFIGURATION_FOLDER_TYPE, "ConfigurationFolderType");
        declared(mv::VISION_STATE_MACHINE_TYPE, "VisionStateMachineType");
        declared(mv::RESULT_READY_EVENT_TYPE, "ResultReadyEventType");
        declared(mv::RESULT_STATE, "ResultStateDataType");
        for (name, id) in mv::STATES {
            declared(id, name);
        }
        for (ids, name) in [
            (mv::RESULT_ID, "ResultIdDataType"),
            (mv::JOB_ID, "JobIdDataType"),
            (mv::PART_ID, "PartIdDataType"),
            (mv::CONFIGURATION_ID, "ConfigurationIdDataType"),
            (mv::RECIPE_ID_INTERNAL, "RecipeIdInternalDataType"),
        ] {
            declared(ids.0, name);
            for encoding in [ids.1, ids.2] {
                let reference = format!("<Reference ReferenceType=\"HasEncoding\">ns=1;i={encoding}</Reference>");
                assert!(text.contains(&reference), "{name}: {reference}");
            }
        }
    }
}
