//! Known-truth tests of the modal identification.

mod identification;
mod util;
