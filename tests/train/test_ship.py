"""codesign.train.ship: a trained checkpoint as the weights the package ships (codesign/models/pretrained/)."""
from __future__ import annotations

import torch
from omegaconf import OmegaConf

from codesign.train.checkpoint import save_checkpoint
from codesign.train.data import build_simulated_data
from codesign.train.model_setup import build_model
from codesign.train.optim import init_weights
from codesign.train.resume import load_trained
from codesign.train.ship import main, shipped_state
from codesign.train.spec import TrainerSpec
from codesign.train.trainer import Trainer
from tests.train._util import tiny_cfg

CPU = torch.device("cpu")


def _trained_checkpoint(tmp_path):
    cfg = tiny_cfg("model=wiener_naf", "trainer.ema=0.5")
    torch.manual_seed(0)
    model = build_model(cfg)
    init_weights(model)
    spec = TrainerSpec.from_config(dict(cfg.trainer)).replace(steps=2, val_every=0, checkpoint_every=0,
                                                              image_every=0)
    tr = Trainer(model=model, data=build_simulated_data(cfg, CPU, 0), spec=spec, run_dir=tmp_path, device=CPU,
                 config=OmegaConf.to_container(cfg, resolve=True), seed=0)
    for _ in range(2):
        tr.train_step()
    return tr.save(), tr


def _same(a: list[dict], b: list[dict]) -> bool:
    return all(x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x) for x, y in zip(a, b))


def test_the_shipped_weights_restore_as_the_checkpoint_s_ema_and_name_its_scenes(tmp_path):
    path, tr = _trained_checkpoint(tmp_path)
    state = shipped_state(path)
    assert set(state) == {"model", "step", "config", "record"} and state["step"] == 2
    assert state["record"]["trained_on"] == {"data.scenes": "builtin", "data.folder": None}
    out = tmp_path / "shipped.pt"
    assert main([str(path), str(out)]) == 0
    # the networks a checkpoint restores with (its EMA averages) are the shipped file's, not the last weights
    ema = [g.state_dict() for g in load_trained(path, CPU)[1]]
    assert _same([g.state_dict() for g in load_trained(out, CPU)[1]], ema)
    assert not _same([g.state_dict() for g in tr.model.generators()], ema)
    assert out.stat().st_size < path.stat().st_size / 2  # no optimizer state
    joint = save_checkpoint(tmp_path / "joint.pt", {**torch.load(path, weights_only=False),
                                                    "mask": {"r": torch.arange(3.0)}})
    assert torch.equal(shipped_state(joint)["mask"]["r"], torch.arange(3.0))  # a learned mask travels with it
    last = tmp_path / "last.pt"
    assert main(["--weights", "last", str(path), str(last)]) == 0
    assert _same([g.state_dict() for g in load_trained(last, CPU)[1]], [g.state_dict() for g in tr.model.generators()])
    assert torch.load(last, weights_only=False)["record"]["weights"] == "last"


def test_an_existing_output_is_never_overwritten(tmp_path, capsys):
    out = tmp_path / "mine.pt"
    out.write_text("keep")
    try:
        main([str(tmp_path / "checkpoint.pt"), str(out)])
    except SystemExit as exit_:
        assert exit_.code == 2
    assert out.read_text() == "keep"
    assert f"out: {out} exists: name a new file" in capsys.readouterr().err
