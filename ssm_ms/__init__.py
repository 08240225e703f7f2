"""ssm-ms: neural state-space models learned by multiple shooting."""
