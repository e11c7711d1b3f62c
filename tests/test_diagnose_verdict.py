"""The diagnosis's verdict on constructed inputs (no fit): a candidate that reproduces part of the water's fields over
the image is a partial step, and the headline names what holds the largest share of the unexplained error."""

from __future__ import annotations

from dataclasses import replace

from eval.diagnose import CandidateResult
from eval.diagnose_verdict import fields_share_check, same_colour, verdict_text

#: The water's fields over the image on a survey whose falloff is of a form the library lacks.
FIELDS = {"form": "multiplicative", "multiplicative_pct": [6.0, 5.0, 4.0], "additive_pct": [3.0, 2.0, 1.0]}


def candidate(change: float = -0.89, share: float | None = 0.68, **kwargs) -> CandidateResult:
    values = {"name": "vignetting_offcentre", "heldout_rmse": 0.01, "change": change,
              "ci95": (change - 0.02, change + 0.02), "p": 0.0, "significant": True, "flattened": "image_position",
              "flattened_drop": 1.0, "params": {"centre_uv": {"value": [0.6, 0.4], "fitted": True}}, "scores": {},
              "structure": {}, "seconds": 0.0, "fields_explained": share}
    return CandidateResult(**{**values, **kwargs})


def test_a_candidate_that_reproduces_part_of_the_fields_is_a_partial_step():
    """Most of the held-out error and the larger part of the fields: accepted as a partial step (the clipped falloff:
    -89 %, 68 % of the fields); too little of the fields, or too little of the error, is refused as before; without
    structured fields, or at 80 % and more, the share decides nothing."""
    assert fields_share_check("vignetting_offcentre", 0.68, -0.89, True) == ("", True)
    assert fields_share_check("vignetting_offcentre", 0.50, -0.50, True) == ("", True)
    for share, change in ((0.30, -0.89), (0.68, -0.30), (0.49, -0.95)):
        reason, partial = fields_share_check("vignetting_offcentre", share, change, True)
        assert "flattens too little of them" in reason and not partial, (share, change)
    assert fields_share_check("vignetting_offcentre", 0.90, -0.10, True) == ("", False)
    assert fields_share_check("vignetting_offcentre", 0.10, -0.89, False) == ("", False)
    assert fields_share_check("caustics", None, -0.89, True) == ("", False)


def test_the_verdict_of_a_partial_step_says_what_remains():
    headline = verdict_text([candidate(partial=True)], [], {}, fields=FIELDS).splitlines()[0]
    assert headline.startswith("missing: vignetting_offcentre — held-out error -89%"), headline
    assert "reproduces 68% of the water's fields over the image: a partial step — add it; what remains is of another " \
           "form (the fields still carry 32% of their structure, multiplicative up to 6 %" in headline, headline
    whole = verdict_text([candidate(share=0.95)], [], {}, fields=FIELDS).splitlines()[0]
    assert "reproduces 95%" in whole and "partial" not in whole, whole


def test_the_headline_names_the_axis_that_holds_the_most_unexplained_error():
    """A camera that sets its white balance per frame: the frame axis holds 37 % of the RMSE, image position 22 %
    (fields of 6 % and 3 %, a candidate refused for them): the headline names the frame axis, image position after
    it; when image position holds more it leads; an accepted candidate leads whatever remains."""
    refused = candidate(change=-0.3, share=0.3, significant=False, implausible="it flattens too little of them")
    scores = {"image_position": 5.0, "frame": 8.0, "range": 1.2}
    structure = {"image_position": 0.22, "frame": 0.37, "range": 0.02}
    lines = verdict_text([refused], ["image_position", "frame"], scores, structure, fields=FIELDS).splitlines()
    assert lines[0].startswith("missing: structure along frame (score 8.0, 37% of the RMSE), the largest share"), lines
    assert lines[1].startswith("then structure on image position of a form not in the library"), lines
    assert lines[2].startswith("no library candidate accepted (best candidate vignetting_offcentre"), lines
    assert any(line.startswith("unexplained structure along: image_position (score 5.0, 22% of the RMSE)")
               for line in lines), lines
    swapped = {"image_position": 0.37, "frame": 0.22}
    lines = verdict_text([refused], ["image_position", "frame"], scores, swapped, fields=FIELDS).splitlines()
    assert lines[0].startswith("missing: structure on image position of a form not in the library"), lines
    no_fields = verdict_text([], ["spatial_frequency", "frame"], {"spatial_frequency": 6.9, "frame": 3.3},
                             {"spatial_frequency": 0.12, "frame": 0.15}).splitlines()
    assert no_fields[0].startswith("missing: structure along frame (score 3.3, 15% of the RMSE)"), no_fields
    assert no_fields[1].startswith("unexplained structure along: spatial_frequency (score 6.9, 12%"), no_fields
    accepted = replace(refused, significant=True, implausible="", change=-0.6, fields_explained=None)
    head = verdict_text([accepted], ["frame"], scores, structure, fields=FIELDS).splitlines()[0]
    assert head.startswith("missing: vignetting_offcentre — held-out error -60%"), head
    assert verdict_text([], [], {}) == "no significant missing effect"


def test_an_offset_of_the_veils_colour_cannot_be_told_from_the_veil():
    """A black level with the colour of the backscatter's B_inf (the falloff of another shape's round 2: 3 degrees
    apart) is a share of the veil left unvignetted and is not accepted; a pedestal of the sensor's colour (the
    simulator's, 38 degrees from this veil) or a candidate that is no offset beside the veil is not concerned."""
    def fitted(offset, b_inf=(0.023, 0.122, 0.146)):
        return {"backscatter": {"b_inf": {"value": list(b_inf), "fitted": True}},
                "black_level": {"offset": {"value": list(offset), "fitted": True}}}

    reason = same_colour("black_level", fitted((0.003, 0.0155, 0.0168)))
    assert reason.startswith("it cannot be told from backscatter") and "3 degrees apart" in reason, reason
    assert same_colour("black_level", fitted((-0.003, -0.0155, -0.0168))) != ""
    assert same_colour("black_level", fitted((0.012, 0.01, 0.008))) == ""
    assert same_colour("black_level", fitted((0.0, 0.0, 0.0))) == ""
    assert same_colour("caustics", fitted((0.003, 0.0155, 0.0168))) == ""
    assert same_colour("black_level", {"black_level": fitted((0.003, 0.0155, 0.0168))["black_level"]}) == ""
