//! The object store's flags, shared by `serve` and `migrate-store`: what reaches the store besides
//! its `s3://bucket/prefix` (docs/operations.md, "Beyond one machine").

use crestscan::service::config::Settings;

#[derive(clap::Args)]
pub struct S3Args {
    /// The object store's endpoint for a store other than AWS, e.g. http://minio:9000.
    #[arg(long, env = "CRESTSCAN_S3_ENDPOINT")]
    s3_endpoint: Option<String>,
    /// The object store's region [default: AWS_REGION, else us-east-1].
    #[arg(long, env = "CRESTSCAN_S3_REGION")]
    s3_region: Option<String>,
    /// The object store's access key [default: AWS_ACCESS_KEY_ID].
    #[arg(long, env = "CRESTSCAN_S3_ACCESS_KEY_ID")]
    s3_access_key_id: Option<String>,
    /// Its secret [default: AWS_SECRET_ACCESS_KEY]; prefer the environment to the command line.
    #[arg(long, env = "CRESTSCAN_S3_SECRET_ACCESS_KEY", hide_env_values = true)]
    s3_secret_access_key: Option<String>,
}

impl S3Args {
    /// Writes the flags given over the settings (the config file's, or the defaults).
    pub fn apply(self, s: &mut Settings) {
        s.s3_endpoint = self.s3_endpoint.or(s.s3_endpoint.take());
        s.s3_region = self.s3_region.or(s.s3_region.take());
        s.s3_access_key_id = self.s3_access_key_id.or(s.s3_access_key_id.take());
        s.s3_secret_access_key = self.s3_secret_access_key.or(s.s3_secret_access_key.take());
    }
}
