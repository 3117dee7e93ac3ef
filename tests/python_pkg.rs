//! The Python package's own tests (`python/tests`, pytest) against this build's `socialflow`
//! binary: Gymnasium's `check_env`, PettingZoo's `parallel_api_test`, seeded determinism, the
//! IDM driver as a Python policy scoring exactly what `socialflow eval-flow --ego idm` scores,
//! and bad arguments raising errors that name them. Runs with the interpreter in
//! `SOCIALFLOW_PKG_PYTHON`, where the package must be installed from this tree first
//! (`tests/run.sh` does: `pip install ./python`); skipped without it, saying so.

use socialflow_e2e::{bin, repo};

#[test]
fn python_package_tests_pass() {
    let Ok(py) = std::env::var("SOCIALFLOW_PKG_PYTHON") else {
        eprintln!("SKIPPED, SOCIALFLOW_PKG_PYTHON not set (tests/run.sh sets it): the Python package's tests are skipped");
        return;
    };
    let out = std::process::Command::new(&py)
        .args(["-m", "pytest", "-q", "-p", "no:cacheprovider", "python/tests"])
        .current_dir(repo())
        .env("SOCIALFLOW_BIN", bin("socialflow"))
        .output()
        .expect("running pytest");
    assert!(
        out.status.success(),
        "pytest failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains(" passed") && !stdout.contains("skipped"),
        "every Python test must run: {stdout}"
    );
}
