//! The scene JSON loader on arbitrary text (against a folder holding a valid mesh and texture),
//! and small loaded scenes through the renderer: typed errors, never a panic.
#![no_main]

use std::path::PathBuf;
use std::sync::OnceLock;

use autodiff::Tape;
use libfuzzer_sys::fuzz_target;
use render_ops::pipeline::Wrt;
use render_ops::scene::Scene;

fn dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("tapestry-fuzz-scene-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(
            d.join("tri.obj"),
            "v -1 -1 0\nv 1 -1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n",
        )
        .unwrap();
        // A 1 x 1 RGB texture that scenes may name as "tex.png".
        render_ops::io::write_png(
            d.join("tex.png"),
            &autodiff::ndarray::Array3::<f64>::from_elem((1, 1, 3), 0.5),
        )
        .unwrap();
        d
    })
}

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(scene) = Scene::<f64>::from_json(text, dir(), "fuzz.json") else {
        return;
    };
    let (w, h) = (
        scene.desc.image.width as u64,
        scene.desc.image.height as u64,
    );
    if w * h > 64 * 64 {
        return; // valid, but too slow to render on every input
    }
    let tape = Tape::new();
    let vars = scene.vars(
        &tape,
        Wrt {
            positions: true,
            colors: true,
            ..Wrt::default()
        },
    );
    if let Ok(img) = scene.render(&vars) {
        let _ = tape.backward(img.sum());
    }
});
