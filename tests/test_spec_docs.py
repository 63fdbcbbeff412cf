"""docs/specs.md is generated from the spec validators' key tables and must be committed up to date."""

import pytest

from wbc_jax.campaign import spec
from wbc_jax.studies import spec_docs


def test_committed_specs_md_is_the_generators_output():
    assert spec_docs.DOCS.read_text() == spec_docs.render(), \
        "docs/specs.md is out of date: run python -m wbc_jax.studies.spec_docs"


def test_every_campaign_key_is_documented():
    text = spec_docs.render()
    for table, schema in (("campaign", spec.CAMPAIGN), ("factors", spec.FACTORS),
                          ("perturbations", spec.PERTURBATIONS)):
        for key in schema:
            assert f"`{table}.{key}`" in text


def test_a_key_without_a_description_fails():
    schema = dict(spec.CAMPAIGN, new_key=(int, 1, 0, 2, False, "[s]"))
    with pytest.raises(KeyError, match="new_key"):
        spec_docs.key_table("campaign", schema, spec_docs.CAMPAIGN_MEANING)
