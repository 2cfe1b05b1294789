//! Training configs come from API clients and their sizes drive memory: out-of-range batch sizes,
//! widths, depths, epochs and threads are refused with a message naming the field, before
//! anything is allocated, and no product of sizes can overflow into a small number.

use trainer::TrainConfig;

fn refused(edit: impl Fn(&mut TrainConfig), want: &str) {
    let mut c = TrainConfig::default();
    edit(&mut c);
    let err = c.validate().expect_err(want).to_string();
    assert!(err.contains(want), "{want:?} not in {err:?}");
}

#[test]
fn sizes_beyond_the_bounds_are_refused() {
    TrainConfig::default().validate().unwrap();
    refused(|c| c.batch_size = 1 << 40, "batch_size");
    refused(|c| c.batch_size = usize::MAX, "batch_size");
    refused(|c| c.epochs = 1_000_000_000, "epochs");
    refused(|c| c.epochs = 0, "epochs");
    refused(|c| c.threads = 100_000, "threads");
    refused(|c| c.architecture.encoder_width = 1 << 20, "width");
    refused(|c| c.architecture.trunk_dims = vec![256; 1000], "trunk layers");
    refused(|c| c.architecture.trunk_dims = vec![usize::MAX / 2], "width");
    refused(
        |c| {
            c.batch_size = 65_536;
            c.architecture.trunk_dims = vec![16_384];
        },
        "too large",
    );
    refused(|c| c.optimizer.lr = f64::INFINITY, "lr");
    // The paper's configurations stay valid.
    let mut c = TrainConfig { batch_size: 4096, ..TrainConfig::default() };
    c.architecture.trunk_dims = vec![1024, 1024];
    c.validate().unwrap();
}
