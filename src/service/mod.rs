//! The service at the edge: axum, sqlx and tokio live here and nowhere below.

pub mod api;
pub mod auth;
pub mod config;
pub mod mqtt;
pub mod mqtt_settings;
pub mod opcua;
pub mod opcua_settings;
pub mod queue;
pub mod startup;
pub mod store;
pub mod telemetry;
pub mod webhook_settings;
pub mod webhooks;
pub mod wire;
pub mod worker;
