//! Regenerates the shipped face model: `cargo run -p tapestry-models --example build_face_model
//! --release [OUT_DIR]` writes `model.json` and the `.npy` arrays (float32) to OUT_DIR
//! (default: `models/data/face`) and prints the component table (markdown) on stdout.

fn main() {
    let out = std::env::args()
        .nth(1)
        .map(std::path::PathBuf::from)
        .unwrap_or_else(models::face::face_dir);
    let model = match models::face::build_face_model() {
        Ok(m) => m,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1);
        }
    };
    if let Err(e) = model.cast::<f32>().save(&out) {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
    eprintln!(
        "wrote {} ({} vertices, {} faces, {} identity, {} expression, {} albedo components)",
        out.display(),
        model.n_vertices(),
        model.n_faces(),
        model.n_id(),
        model.n_exp(),
        model.n_albedo()
    );
    println!("| basis | k | name | sigma | peak at 1 sigma | RMS at 1 sigma |");
    println!("|---|---|---|---|---|---|");
    for c in models::face::component_table(&model) {
        let unit = if c.kind == "albedo" { "" } else { " mm" };
        println!(
            "| {} | {} | `{}` | {:.3}{unit} | {:.2}{unit} | {:.3}{unit} |",
            c.kind, c.index, c.name, c.sigma, c.peak, c.rms
        );
    }
}
