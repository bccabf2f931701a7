//! The command line's value enums: copies of the library's with `clap::ValueEnum` (the library
//! does not depend on clap), same variants, names, aliases and doc comments (`--help` prints them
//! as the values' help); tests/it/cli.rs checks the names against the library's.

/// For each `$cli => $lib { variants }`: the enum `$cli` above (variant doc comments and
/// `#[value(...)]` attributes kept, its doc linking to `$lib`) and `From<$cli> for $lib`.
macro_rules! value_enum {
    ($(
        $cli:ident => $lib:path {
            $( $(#[$vmeta:meta])* $variant:ident ),* $(,)?
        }
    )*) => {$(
        #[doc = concat!("The command line's [`", stringify!($lib), "`].")]
        #[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
        pub enum $cli {
            $( $(#[$vmeta])* $variant ),*
        }

        impl From<$cli> for $lib {
            fn from(v: $cli) -> Self {
                match v { $( $cli::$variant => Self::$variant ),* }
            }
        }
    )*};
}

value_enum! {
    LoopKind => crate::model::spec::LoopKind {
        /// The thesis's idealisation: continuous controllers, no hold (its tables use it).
        Continuous,
        /// The spacecraft's loop: discrete controllers at the control rate, held commands.
        Digital,
    }

    ScenarioSet => crate::accel::job::ScenarioSet { Guess, Truth }

    Estimator => crate::fit::Estimator {
        /// `rho = r^2` (Gaussian likelihood).
        Squared,
        /// `rho = |r|` (thesis: "mean absolute deviation").
        Absolute,
        /// `rho = log(1 + r^2)` (Lorentzian; thesis: "mean logarithmic deviation").
        Log,
    }

    Matrix => crate::design::criteria::Matrix {
        #[value(alias = "info")]
        Information,
        #[value(alias = "cov")]
        Covariance,
    }

    Choice => crate::design::criteria::Choice { D, E, T, All }

    Scaling => crate::design::criteria::Scaling { Natural, Nominal, Standard }

    Layout => crate::design::space::Layout {
        /// Multi-experiment single-input: Exp. 1 on oi1, Exp. 2 on oi12 (thesis sec. 5.3).
        Separate,
        /// Single-experiment multi-input: Exp. 3 injects on both inputs at once (thesis sec. 5.4).
        Simultaneous,
    }

    Engine => crate::sim::Engine {
        /// Templates plus coloured noise of the continuous loop's PSD (fast; the campaigns'
        /// default).
        FrequencyDomain,
        /// The digital loop stepped at simulate_hz (plant integrated exactly, discrete
        /// controllers, held commands), decimated with the anti-alias FIR.
        TimeDomain,
    }

    Rate => crate::sim::Rate {
        /// Simulate at the model's simulate_hz and decimate with the anti-alias FIR (thesis).
        Decimated,
        /// Simulate directly at analyse_hz (ideal anti-alias decimation; what frequency-domain
        /// campaigns use).
        Analysis,
    }

    Whitening => crate::analysis::Whitening {
        /// The dataset's noise run if it has one, else the model's noise PSD.
        Auto,
        /// The dataset's noise run (an error if it has none).
        Noise,
        /// The model's noise cross-PSD at the starting point.
        Model,
    }
}
