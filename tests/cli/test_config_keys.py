"""Unknown configuration keys: every section of the configuration refuses them, naming the file, the key, the section
and the nearest valid name. The sections are found by walking the models by reflection, so a new one is covered."""
from __future__ import annotations

import difflib
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel

from neuralslicer.config import SliceConfig
from neuralslicer.errors import InputError
from neuralslicer.motion.profile import MachineProfile
from neuralslicer.toolpath.config import toolpath_config_from_dict


def _models(annotation: object) -> list[type[BaseModel]]:
    """The pydantic models in a field's annotation, found independently of the code under test."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in getattr(annotation, "__args__", ()) for m in _models(arg)]


def sections(model: type[BaseModel], path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], type[BaseModel]]]:
    """(key path, model) of the model and of every section nested in it, depth first."""
    out = [(path, model)]
    for name, field in model.model_fields.items():
        for sub in _models(field.annotation):
            out += sections(sub, path + (name,))
    return out


def _typo(name: str) -> str:
    """A misspelling of ``name``: its second letter dropped, its last doubled (``layer_height`` -> ``lyer_heightt``)."""
    return name[0] + name[2:] + name[-1] if len(name) > 3 else name + name[-1]


def _nested(path: tuple[str, ...], leaf: dict) -> dict:
    for key in reversed(path):
        leaf = {key: leaf}
    return leaf


SECTIONS = sections(SliceConfig)


def test_the_walk_finds_every_section() -> None:
    paths = {".".join(p) for p, _ in SECTIONS}
    # the sections the issue measured accepting unknown keys, and nested ones several levels down
    assert {"", "samples", "cage", "layers", "toolpath", "neural", "neural.optim", "neural.loss", "neural.loss.head",
            "s3", "s3_oneshot"} <= paths
    assert len(SECTIONS) >= 12


@pytest.mark.parametrize("path,model", SECTIONS, ids=[".".join(p) or "(top)" for p, _ in SECTIONS])
def test_every_section_forbids_unknown_keys_and_names_the_nearest(path, model, tmp_path: Path) -> None:
    assert model.model_config.get("extra") == "forbid", model.__name__
    name = max(model.model_fields, key=len)
    typo = _typo(name)
    assert typo not in model.model_fields
    nearest = difflib.get_close_matches(typo, list(model.model_fields), n=1)
    assert nearest == [name]                                  # the expectation, independently of the message
    cfg = tmp_path / "config.yaml"
    cfg.write_text(yaml.safe_dump(_nested(path, {typo: 1})))
    with pytest.raises(InputError) as caught:
        SliceConfig.from_yaml(cfg)
    text = str(caught.value)
    section = ".".join(path)
    assert text.startswith(f"{cfg}: {'.'.join(path + (typo,))}: ")   # the file, then the key
    assert f"unknown key {typo!r}" in text
    assert (f"in section {section!r}" if section else "at the top level") in text
    assert text.endswith(f"did you mean {name!r}?")
    assert "\n" not in text


@pytest.mark.parametrize("text,key,hint", [
    ("layers: {layer_hight: 0.6}", "layers.layer_hight", "did you mean 'layer_height'?"),
    ("cage: {elementz: 5}", "cage.elementz", "did you mean 'n_elements'?"),
    ("samples: {n: 3}", "samples.n", "valid keys: n_samples, k, seed"),
    ("neural: {network: {hidden_layer: 3}}", "neural.network.hidden_layer", "did you mean 'hidden_layers'?"),
])
def test_the_issues_examples_are_refused(text: str, key: str, hint: str, tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text + "\n")
    with pytest.raises(InputError, match="unknown key") as caught:
        SliceConfig.from_yaml(cfg)
    assert caught.value.where == f"{cfg}: {key}" and caught.value.message.endswith(hint)


def test_valid_keys_still_load_and_other_errors_keep_their_message(tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("layers: {layer_height: 0.6}\ncage: {n_elements: 500}\nsamples: {n_samples: 300}\n")
    loaded = SliceConfig.from_yaml(cfg)
    assert (loaded.layers.layer_height, loaded.cage.n_elements, loaded.samples.n_samples) == (0.6, 500, 300)
    cfg.write_text("layers: {layer_height: -1}\n")
    with pytest.raises(InputError, match="greater than 0"):
        SliceConfig.from_yaml(cfg)


def test_toolpath_settings_file_names_the_nearest_key() -> None:
    with pytest.raises(InputError, match=r"line_widht: unknown key 'line_widht' at the top level; did you mean "
                                         r"'line_width'\?"):
        toolpath_config_from_dict({"line_widht": 0.4}, where="tp.yaml")


def test_machine_profile_sections_forbid_unknown_keys() -> None:
    # read-only: the profile models (neuralslicer/motion/profile.py) forbid extras themselves
    for path, model in sections(MachineProfile):
        assert model.model_config.get("extra") == "forbid", ".".join(path) or model.__name__


@pytest.mark.parametrize("text,where,hint", [
    ("unit: mm\ncomponents:\n  - {type: mesh, file: part.stl}\n", "unit", "at the top level; did you mean 'units'?"),
    ("components:\n  - {type: mesh, fiel: part.stl}\n", "components[0].fiel",
     "in section 'components'; did you mean 'file'?"),
    ("components:\n  - {type: struts, file: l.txt, raduis: 1}\n", "components[0].raduis",
     "in section 'components'; did you mean 'radius'?"),
    ("components:\n  - {type: mesh, file: part.stl}\nfea:\n  material: {youngs_modulus: 3}\n",
     "fea.material.youngs_modulus", "in section 'fea.material'; did you mean 'youngs_modulus_mpa'?"),
])
def test_model_specs_name_the_nearest_key_too(text: str, where: str, hint: str, tmp_path: Path) -> None:
    from neuralslicer.model.spec import load_spec

    (tmp_path / "part.stl").write_text("solid x\nendsolid x\n")
    spec = tmp_path / "model.yaml"
    spec.write_text(text)
    with pytest.raises(InputError) as caught:
        load_spec(spec)
    assert caught.value.message.startswith(f"{where}: unknown key ") and caught.value.message.endswith(hint)
    assert caught.value.where.startswith(str(spec))
