//! The records over TLS: PostgreSQL reached with the server verified (`sslmode=verify-full`),
//! and refused where its certificate is not the trusted one.

use crate::common::{database_for, postgres_tls_root, self_signed};
use crestscan::service::store::{Database, Store};

#[tokio::test]
async fn postgres_is_reached_over_verified_tls_and_a_stranger_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let root = postgres_tls_root();
    let url = format!("{}?sslmode=verify-full&sslrootcert={}", database_for(dir.path()), root.display());
    let (uploads, tmp) = (dir.path().join("uploads"), dir.path().join("tmp"));
    let store = Store::connect(&Database::Postgres(url), &uploads, &tmp).await.unwrap();
    let encrypted = store.count("SELECT COUNT(*) FROM pg_stat_ssl WHERE pid = pg_backend_pid() AND ssl").await;
    assert_eq!(encrypted.unwrap(), 1, "the connection is encrypted");
    store.close().await;

    // A root that did not sign the server's certificate: the server is not trusted.
    let (stranger, _, _) = self_signed(dir.path(), "stranger");
    let url = format!("{}?sslmode=verify-full&sslrootcert={}", database_for(dir.path()), stranger.display());
    let err = Store::connect(&Database::Postgres(url), &uploads, &tmp).await.err().expect("refused");
    let text = err.to_string();
    assert!(text.to_lowercase().contains("certificate"), "{text}");
}
