//! Device-resident training step of the Sun-aware model. (Work in progress.)
