//! Scenario model: map, objects, ego log, route, camera rig and recorded frames. Importers in [`import`].
//! Never imports `ash`.
pub mod camera;
