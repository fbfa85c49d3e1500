//! crispen's geometry: meshes and the method that sharpens them.
//!
//! - [`mesh`]: reading STL, OBJ and 3MF, cleaning, placing and writing meshes.
//! - [`enhance`]: adaptive unsharp masking of the geometry (Herholz, Koch, Boubekeur and
//!   Alexa 2017): the operators, the solves, the bands and the strength for a print's size.
//!
//! It needs nothing of slicing, printers or the farm; the farm's crate re-exports both as
//! `crispen::mesh` and `crispen::enhance`.

#![warn(unreachable_pub)]

pub mod enhance;
pub mod mesh;
