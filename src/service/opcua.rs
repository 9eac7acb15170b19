//! An OPC UA server modelled on OPC 40100 (OPC UA for Machine Vision), `opcua_endpoint`
//! (docs/interchange.md, "OPC UA"). Under `Objects/VisionSystem`, in the namespace
//! [`NAMESPACE`]:
//!
//! - `VisionStateMachine/CurrentState`: `Preoperational` until the first look at the store,
//!   `Operational` while the store reads and takes writes, `Error` (with `ErrorReason`) while it
//!   does not, `Halted` once the service is stopping; `ExecutionState` below it: `Ready` (nothing
//!   queued or running) or `Executing`, with the queued and running inspections counted;
//! - `RecipeManagement/Recipes/default`: the pipeline options a submission gets unless it overrides
//!   them (`Content`, JSON);
//! - `ConfigurationManagement/Configurations/<station>`: each station's status (qualified,
//!   suspended, …) and its reason;
//! - `ResultManagement/LastResult`: the last succeeded inspection's result;
//! - `ResultReadyEventType` events (the VisionSystem is their source and notifier; the Server
//!   object sees them too) for each succeeded inspection: its id, verdict, decision, review flag,
//!   station, serial, connection, report link, and per thread its number, mean height,
//!   uncertainty, finding and black-crest length.
//!
//! The companion specification's own NodeSet (its type NodeIds and the structured
//! `ResultDataType`) is not loaded: the names follow it, the types are this namespace's.
//!
//! Each process serving the API with an endpoint follows the database's `events` table (as the MQTT
//! publisher does, but every server sees every event), so results another process finished are
//! announced too. Anonymous sessions are refused when the service requires API keys; a client then
//! presents a user name token whose password is an API key with the `read` scope.

use crate::service::auth::{self, Scope};
use crate::service::config::{AuthMode, Settings};
use crate::service::opcua_settings::Endpoint;
use crate::service::store::{Store, StoreError};
use opcua::Event;
use opcua::crypto::SecurityPolicy;
use opcua::nodes::BaseEventType;
use opcua::server::address_space::{AddressSpace, EventNotifier, ObjectBuilder, ObjectTypeBuilder, VariableBuilder};
use opcua::server::authenticator::{AuthManager, Password, UserToken, user_pass_security_policy_id};
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::memory::{SimpleNodeManager, simple_node_manager};
use opcua::server::{ANONYMOUS_USER_TOKEN_ID, Server, ServerBuilder, ServerEndpoint, ServerHandle};
use opcua::types::{
    BuildInfo, ByteString, DataTypeId, DataValue, DateTime, Error as UaError, LocalizedText, MessageSecurityMode,
    NodeId, ObjectId, ObjectTypeId, QualifiedName, StatusCode, UAString, UserTokenPolicy, UserTokenType,
    VariableTypeId, Variant,
};
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::watch;

/// The namespace of crestscan's nodes and types.
pub const NAMESPACE: &str = "urn:crestscan:machine-vision";
/// How often the server looks for new events.
const POLL: Duration = Duration::from_millis(500);
/// How often it checks that the store reads and takes a write (the check commits a row, so not at
/// every poll).
const HEALTH: Duration = Duration::from_secs(5);
/// Events read at a time.
const BATCH: i64 = 100;

/// A succeeded inspection, as OPC 40100's ResultReadyEventType announces a result (flattened:
/// the per-thread summary as parallel arrays, index i for the thread `ThreadNumbers[i]`).
#[derive(Event)]
#[opcua(identifier = "s=ResultReadyEventType", namespace = "urn:crestscan:machine-vision")]
pub struct ResultReadyEvent {
    base: BaseEventType,
    own_namespace_index: u16,
    /// The inspection's id.
    result_id: String,
    is_partial: bool,
    /// 1 conforms, 2 does not conform, 0 indeterminate (the ISO 14253-1 decision).
    result_state: i32,
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
        self.get_field(
            &ObjectTypeId::BaseEventType.into(),
            opcua::types::AttributeId::Value,
            &opcua::types::NumericRange::None,
            &[QualifiedName::new(self.own_namespace_index, name)],
        )
    }
}

/// The event type's fields as properties of its type node, name, data type and whether an array:
/// a client builds its event filter from them.
const RESULT_FIELDS: [(&str, DataTypeId, bool); 15] = [
    ("ResultId", DataTypeId::String, false),
    ("IsPartial", DataTypeId::Boolean, false),
    ("ResultState", DataTypeId::Int32, false),
    ("Verdict", DataTypeId::String, false),
    ("Decision", DataTypeId::String, false),
    ("ReviewRequired", DataTypeId::Boolean, false),
    ("Station", DataTypeId::String, false),
    ("Serial", DataTypeId::String, false),
    ("Connection", DataTypeId::String, false),
    ("Report", DataTypeId::String, false),
    ("ThreadNumbers", DataTypeId::Int32, true),
    ("ThreadMeanHeightsMm", DataTypeId::Double, true),
    ("ThreadHeightUncertaintiesMm", DataTypeId::Double, true),
    ("ThreadFindings", DataTypeId::String, true),
    ("ThreadBlackCrestLengthsMm", DataTypeId::Double, true),
];

/// Unix milliseconds as OPC UA's time (100 ns ticks since 1601-01-01).
fn ua_time(ms: i64) -> DateTime {
    DateTime::from((ms + 11_644_473_600_000) * 10_000)
}

/// The result state a decision reads as (1 good, 2 bad, 0 undecided).
pub fn result_state(decision: Option<&str>) -> i32 {
    use crate::pipeline::uncertainty::Decision;
    match decision {
        Some(d) if d == Decision::Conforms.as_str() => 1,
        Some(d) if d == Decision::DoesNotConform.as_str() => 2,
        _ => 0,
    }
}

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
    ns: u16,
    vision_system: NodeId,
    current_state: NodeId,
    error_reason: NodeId,
    execution_state: NodeId,
    queued: NodeId,
    running: NodeId,
    configurations: NodeId,
}

impl Nodes {
    fn id(&self, path: &str) -> NodeId {
        NodeId::new(self.ns, path.to_string())
    }
}

/// The server, bound and built, not yet serving.
pub struct OpcUaServer {
    server: Server,
    handle: ServerHandle,
    listener: TcpListener,
    manager: Arc<SimpleNodeManager>,
    nodes: Nodes,
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
            .with_node_manager(simple_node_manager(
                NamespaceMetadata { namespace_uri: NAMESPACE.to_owned(), ..Default::default() },
                "crestscan",
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
            .get_of_type::<SimpleNodeManager>()
            .ok_or("OPC UA server: its node manager is missing")?;
        let ns = handle.get_namespace_index(NAMESPACE).ok_or("OPC UA server: its namespace is missing")?;
        let nodes = {
            let address_space = manager.address_space();
            let mut space = address_space.write();
            build_address_space(&mut space, ns)
        };
        Ok(OpcUaServer { server, handle, listener, manager, nodes, url })
    }

    /// The endpoint's URL, with the port taken.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// Serves until `stop`, following the events and the store's state.
    pub async fn run(self, store: Store, mut stop: watch::Receiver<bool>) {
        let OpcUaServer { server, handle, listener, manager, nodes, url } = self;
        tracing::info!(%url, "OPC UA server listening");
        let serving = tokio::spawn(server.run_with(listener));
        let mut follower = Follower { store, handle: handle.clone(), manager, nodes, cursor: None, checked: None };
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

/// The type and instance nodes (module docs).
fn build_address_space(space: &mut AddressSpace, ns: u16) -> Nodes {
    let id = |path: &str| NodeId::new(ns, path.to_string());
    let event_type = ResultReadyEvent::event_type_id_from_index(ns);
    ObjectTypeBuilder::new(&event_type, QualifiedName::new(ns, "ResultReadyEventType"), "ResultReadyEventType")
        .is_abstract(false)
        .subtype_of(ObjectTypeId::BaseEventType)
        .description("A succeeded inspection's result (modelled on OPC 40100's ResultReadyEventType)")
        .insert(space);
    for (name, data_type, array) in RESULT_FIELDS {
        let mut field =
            VariableBuilder::new(&id(&format!("ResultReadyEventType/{name}")), QualifiedName::new(ns, name), name)
                .property_of(event_type.clone())
                .data_type(data_type)
                .has_type_definition(VariableTypeId::PropertyType)
                .has_modelling_rule(ObjectId::ModellingRule_Mandatory);
        if array {
            field = field.value_rank(1);
        }
        field.insert(space);
    }
    let system_type = id("VisionSystemType");
    ObjectTypeBuilder::new(&system_type, QualifiedName::new(ns, "VisionSystemType"), "VisionSystemType")
        .is_abstract(false)
        .subtype_of(ObjectTypeId::BaseObjectType)
        .generates_event(event_type.clone())
        .insert(space);

    let system = id("VisionSystem");
    ObjectBuilder::new(&system, QualifiedName::new(ns, "VisionSystem"), "crestscan VisionSystem")
        .description("crestscan's thread inspection, modelled on OPC 40100 (Machine Vision)")
        .event_notifier(EventNotifier::SUBSCRIBE_TO_EVENTS)
        .organized_by(ObjectId::ObjectsFolder)
        .has_type_definition(system_type)
        .insert(space);
    let object = |space: &mut AddressSpace, path: &str, name: &str, parent: &NodeId| {
        ObjectBuilder::new(&id(path), QualifiedName::new(ns, name), name)
            .component_of(parent.clone())
            .has_type_definition(ObjectTypeId::BaseObjectType)
            .insert(space);
        id(path)
    };
    let variable =
        |space: &mut AddressSpace, path: &str, name: &str, parent: &NodeId, value: Variant, data_type: DataTypeId| {
            VariableBuilder::new(&id(path), QualifiedName::new(ns, name), name)
                .component_of(parent.clone())
                .data_type(data_type)
                .has_type_definition(VariableTypeId::BaseDataVariableType)
                .value(value)
                .insert(space);
            id(path)
        };

    let machine = object(space, "VisionStateMachine", "VisionStateMachine", &system);
    let current_state = variable(
        space,
        "VisionStateMachine/CurrentState",
        "CurrentState",
        &machine,
        LocalizedText::from("Preoperational").into(),
        DataTypeId::LocalizedText,
    );
    let error_reason =
        variable(space, "VisionStateMachine/ErrorReason", "ErrorReason", &machine, "".into(), DataTypeId::String);
    let execution_state = variable(
        space,
        "VisionStateMachine/ExecutionState",
        "ExecutionState",
        &machine,
        LocalizedText::from("Ready").into(),
        DataTypeId::LocalizedText,
    );
    let queued = variable(
        space,
        "VisionStateMachine/InspectionsQueued",
        "InspectionsQueued",
        &machine,
        0i64.into(),
        DataTypeId::Int64,
    );
    let running = variable(
        space,
        "VisionStateMachine/InspectionsRunning",
        "InspectionsRunning",
        &machine,
        0i64.into(),
        DataTypeId::Int64,
    );

    let recipes_manager = object(space, "RecipeManagement", "RecipeManagement", &system);
    let recipes = object(space, "RecipeManagement/Recipes", "Recipes", &recipes_manager);
    let default = object(space, "RecipeManagement/Recipes/default", "default", &recipes);
    variable(
        space,
        "RecipeManagement/Recipes/default/ExternalId",
        "ExternalId",
        &default,
        "default".into(),
        DataTypeId::String,
    );
    let options = serde_json::to_string(&crate::pipeline::PipelineOptions::default()).unwrap_or_default();
    variable(
        space,
        "RecipeManagement/Recipes/default/Content",
        "Content",
        &default,
        options.into(),
        DataTypeId::String,
    );

    let configurations_manager = object(space, "ConfigurationManagement", "ConfigurationManagement", &system);
    let configurations =
        object(space, "ConfigurationManagement/Configurations", "Configurations", &configurations_manager);

    let results = object(space, "ResultManagement", "ResultManagement", &system);
    let last_result = object(space, "ResultManagement/LastResult", "LastResult", &results);
    for (name, data_type, array) in RESULT_FIELDS {
        let value = match (array, data_type) {
            (true, DataTypeId::Int32) => Variant::from(Vec::<i32>::new()),
            (true, DataTypeId::Double) => Variant::from(Vec::<f64>::new()),
            (true, _) => Variant::from(Vec::<String>::new()),
            (false, DataTypeId::Boolean) => false.into(),
            (false, DataTypeId::Int32) => 0i32.into(),
            _ => "".into(),
        };
        let mut field = VariableBuilder::new(
            &id(&format!("ResultManagement/LastResult/{name}")),
            QualifiedName::new(ns, name),
            name,
        )
        .component_of(last_result.clone())
        .data_type(data_type)
        .has_type_definition(VariableTypeId::BaseDataVariableType)
        .value(value);
        if array {
            field = field.value_rank(1);
        }
        field.insert(space);
    }
    Nodes { ns, vision_system: system, current_state, error_reason, execution_state, queued, running, configurations }
}

/// Follows the events table and the store's state into the address space.
struct Follower {
    store: Store,
    handle: ServerHandle,
    manager: Arc<SimpleNodeManager>,
    nodes: Nodes,
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
                ObjectBuilder::new(&object, QualifiedName::new(self.nodes.ns, name), name)
                    .component_of(self.nodes.configurations.clone())
                    .has_type_definition(ObjectTypeId::BaseObjectType)
                    .insert(&mut *space);
                for (id, field) in [(&status_id, "Status"), (&reason_id, "StatusReason")] {
                    VariableBuilder::new(id, QualifiedName::new(self.nodes.ns, field), field)
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
        let ns = self.nodes.ns;
        let event_type = ResultReadyEvent::event_type_id_from_index(ns);
        let verdict = row.verdict.clone().unwrap_or_default();
        let decision = row.decision.clone().unwrap_or_default();
        let message = format!("inspection {id}: {verdict}, {decision}");
        let time = ua_time(row.finished_at.unwrap_or(row.updated_at));
        let base = BaseEventType::new(event_type, ByteString::from(id.as_bytes().to_vec()), message, time)
            .set_source_node(self.nodes.vision_system.clone())
            .set_source_name(UAString::from("VisionSystem"))
            .set_severity(if row.review_required == Some(true) { 500 } else { 100 });
        let event = ResultReadyEvent {
            base,
            own_namespace_index: ns,
            result_id: id.to_string(),
            is_partial: false,
            result_state: result_state(row.decision.as_deref()),
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
        };
        // LastResult reads each field from the event as a subscriber's select clause would, so
        // that the two cannot differ (a unit test checks every field is found).
        for (name, _, _) in RESULT_FIELDS {
            self.set(&self.nodes.id(&format!("ResultManagement/LastResult/{name}")), event.field(name));
        }
        self.handle
            .subscriptions()
            .notify_events([(&event as &dyn opcua::nodes::Event, &self.nodes.vision_system)].into_iter());
        tracing::debug!(inspection = id, seq, "OPC UA: result announced");
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every field the type node and LastResult name is one the event has, of the declared type
    /// and shape: the struct, [`RESULT_FIELDS`] and LastResult cannot drift apart.
    #[test]
    fn every_declared_field_is_the_events_own() {
        let ns = 2;
        let base = BaseEventType::new(
            ResultReadyEvent::event_type_id_from_index(ns),
            ByteString::from(b"id".to_vec()),
            "message",
            DateTime::now(),
        );
        let event = ResultReadyEvent {
            base,
            own_namespace_index: ns,
            result_id: "0190-id".into(),
            is_partial: false,
            result_state: 1,
            verdict: "accept".into(),
            decision: "conforms".into(),
            review_required: true,
            station: "line-3".into(),
            serial: "SN-1".into(),
            connection: "buttress".into(),
            report: "/v1/inspections/0190-id/report".into(),
            thread_numbers: vec![1, 2],
            thread_mean_heights_mm: vec![1.57, 1.58],
            thread_height_uncertainties_mm: vec![0.004, 0.005],
            thread_findings: vec!["conforms".into(), "indeterminate".into()],
            thread_black_crest_lengths_mm: vec![0.0, 1.5],
        };
        for (name, data_type, array) in RESULT_FIELDS {
            let value = event.field(name);
            let expected = match (data_type, array) {
                (DataTypeId::String, false) => matches!(value, Variant::String(_)),
                (DataTypeId::Boolean, false) => matches!(value, Variant::Boolean(_)),
                (DataTypeId::Int32, false) => matches!(value, Variant::Int32(_)),
                (_, true) => matches!(&value, Variant::Array(a) if a.values.len() == 2),
                _ => false,
            };
            assert!(expected, "{name}: {value:?}");
        }
        assert_eq!(event.field("ResultId"), Variant::from("0190-id"));
        assert_eq!(event.field("ThreadMeanHeightsMm"), Variant::from(vec![1.57, 1.58]));
        assert_eq!(event.field("NoSuchField"), Variant::Empty);
    }
}
