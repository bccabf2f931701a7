//! The forward model: what the closed loop makes of known inputs. Noise-free responses
//! ("templates", thesis eq. "templates") and their analytic parameter derivatives on a
//! zero-padded FFT grid (`templates`), and the frequency-domain Fisher information of an
//! injection design (`fisher`, thesis sec. 4.4.6 and ch. 5). Simulation, fitting, design and
//! diagnosis all build on it.

pub mod fisher;
pub mod templates;

pub use templates::{GridFilter, TemplateEngine};
