//! The integration tests, one module per former test binary, linked once (each binary linked
//! arrow and parquet). Shared fixtures are in `common`.

mod common;

mod accel;
mod analytic_model;
mod auxiliary;
mod campaign;
mod campaign_time_domain;
mod campaign_xy;
mod cli;
mod codecs;
mod config;
mod design;
mod design_xy;
mod diagnose;
mod diagnose_effects;
mod fit;
mod guidance_design;
mod guidance_rate;
mod holes;
mod hostile;
mod io;
mod lengths;
mod man;
mod memory;
mod metadata;
mod missing_rows;
mod model;
mod nyquist_null;
mod overwrite;
mod plots;
mod posterior;
mod redesign;
mod simulation;
mod slurm;
mod spectral;
mod third_model;
mod time_domain;
mod time_domain_diagnose;
mod time_domain_effects;
mod transient;
mod units;
mod whittle;
mod xy_commands;
mod xy_diagnose;
mod xy_model;
