//! The OBJ loader on arbitrary text: a typed error or a valid mesh, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use render_ops::obj::parse_obj_str;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    if let Ok(mesh) = parse_obj_str::<f64>(&text) {
        let nv = mesh.positions.len();
        assert!(mesh.positions.iter().flatten().all(|x| x.is_finite()));
        assert!(mesh.faces.iter().flatten().all(|&i| (i as usize) < nv));
    }
    let _ = parse_obj_str::<f32>(&text);
});
