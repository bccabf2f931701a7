//! The search: the problem planned once per noise run ([`problem`]), the forward selection
//! ([`selection`]) with its scores ([`score`]), the observers of its notes ([`observer`]) and
//! the run that strings them together ([`run`]).

pub(crate) mod bayes;
pub mod observer;
pub mod problem;
pub mod run;
pub mod score;
pub mod selection;
