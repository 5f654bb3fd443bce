//! The concealed-effect corpus (being written).
