//! The command line's value enums: each is the library enum of the same name with
//! `clap::ValueEnum` (the library does not depend on clap), with the same variants, names,
//! aliases and doc comments (which `--help` prints as the values' help), and `From` both ways
//! (tests/it/cli.rs checks the names against the library's).

/// For each `$cli => $lib { variants }`: a `clap::ValueEnum` copy of the library enum `$lib`
/// named `$cli`, variant for variant, and the conversions. Variant doc comments and
/// `#[value(...)]` attributes are kept.
macro_rules! value_enum {
    ($(
        $(#[$meta:meta])*
        $cli:ident => $lib:path {
            $( $(#[$vmeta:meta])* $variant:ident ),* $(,)?
        }
    )*) => {$(
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
        pub enum $cli {
            $( $(#[$vmeta])* $variant ),*
        }

        impl From<$cli> for $lib {
            fn from(v: $cli) -> Self {
                match v {
                    $( $cli::$variant => Self::$variant ),*
                }
            }
        }

        impl From<$lib> for $cli {
            fn from(v: $lib) -> Self {
                type Lib = $lib;
                match v {
                    $( Lib::$variant => $cli::$variant ),*
                }
            }
        }
    )*};
}

value_enum! {
    /// Which frequency response the model uses (`model::spec::LoopKind`).
    LoopKind => crate::model::spec::LoopKind {
        /// The thesis's idealisation: continuous controllers, no hold (its tables use it).
        Continuous,
        /// The spacecraft's loop: discrete controllers at the control rate, held commands.
        Digital,
    }

    /// Which parameter set of a scenario (`accel::job::ScenarioSet`).
    ScenarioSet => crate::accel::job::ScenarioSet { Guess, Truth }

    /// The L-estimator of a fit (`fit::Estimator`).
    Estimator => crate::fit::Estimator {
        /// `rho = r^2` (Gaussian likelihood).
        Squared,
        /// `rho = |r|` (thesis: "mean absolute deviation").
        Absolute,
        /// `rho = log(1 + r^2)` (Lorentzian; thesis: "mean logarithmic deviation").
        Log,
    }

    /// Information or covariance matrix (`design::criteria::Matrix`).
    Matrix => crate::design::criteria::Matrix {
        #[value(alias = "info")]
        Information,
        #[value(alias = "cov")]
        Covariance,
    }

    /// The criteria an optimisation is asked for (`design::criteria::Choice`).
    Choice => crate::design::criteria::Choice { D, E, T, All }

    /// Parameter scaling for T and E (`design::criteria::Scaling`).
    Scaling => crate::design::criteria::Scaling { Natural, Nominal, Standard }

    /// How the experiments use the inputs (`design::space::Layout`).
    Layout => crate::design::space::Layout {
        /// Multi-experiment single-input: Exp. 1 on oi1, Exp. 2 on oi12 (thesis sec. 5.3).
        Separate,
        /// Single-experiment multi-input: Exp. 3 injects on both inputs at once (thesis sec. 5.4).
        Simultaneous,
    }

    /// The simulation engine (`sim::Engine`).
    Engine => crate::sim::Engine {
        /// Templates plus coloured noise of the continuous loop's PSD (fast; the campaigns'
        /// default).
        FrequencyDomain,
        /// The digital loop stepped at simulate_hz (plant integrated exactly, discrete
        /// controllers, held commands), decimated with the anti-alias FIR.
        TimeDomain,
    }

    /// The simulation path of a dataset (`sim::Rate`).
    Rate => crate::sim::Rate {
        /// Simulate at the model's simulate_hz and decimate with the anti-alias FIR (thesis).
        Decimated,
        /// Simulate directly at analyse_hz (ideal anti-alias decimation; what frequency-domain
        /// campaigns use).
        Analysis,
    }

    /// Where the whitening filter should come from (`analysis::Whitening`).
    Whitening => crate::analysis::Whitening {
        /// The dataset's noise run if it has one, else the model's noise PSD.
        Auto,
        /// The dataset's noise run (an error if it has none).
        Noise,
        /// The model's noise cross-PSD at the starting point.
        Model,
    }
}
