//! Parametric models.
