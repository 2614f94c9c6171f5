//! The lab's static and dynamic fits.
