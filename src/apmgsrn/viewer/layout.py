"""The page's layout (trame + Vuetify): app bar, side panel of controls, the image with its overlay."""

from __future__ import annotations

from apmgsrn.viewer.settings import RenderSettings
from apmgsrn.viewer.webpage import VIEWER_SCRIPT, VIEWER_STYLE


def build_page(server, title: str, settings: RenderSettings):
    """Lay the page out on a trame server; widgets are bound to the state names :class:`PageState` fills.

    Args:
        server: the trame server.
        title: shown in the app bar.
        settings: the starting settings (initial widget values).

    Returns:
        The trame layout.
    """
    # trame is the optional [viewer] extra: imported when a page is built, never with the package.
    from trame.ui.vuetify3 import VAppLayout
    from trame.widgets import client, html
    from trame.widgets import vuetify3 as v
    from trame_client.widgets.core import HtmlElement

    with VAppLayout(server, full_height=True) as layout:
        client.Style(VIEWER_STYLE)
        client.Script(VIEWER_SCRIPT)
        with v.VAppBar(density="compact", elevation=1):
            html.Div(title, classes="text-h6 ml-4 mr-6", id="apm-title")
            html.Div("{{ source_description }}", classes="text-body-2 text-medium-emphasis", id="apm-source")
            v.VSpacer()
            v.VSwitch(
                v_model=("overlay", False),
                label="grids & bricks",
                disabled=("!overlay_available",),
                hide_details=True,
                density="compact",
                color="primary",
                classes="mr-4 flex-grow-0",
                id="apm-overlay-switch",
            )
            v.VBtn("reset view", click="window.apmgsrnViewer.resetView()", variant="text", id="apm-reset")
            v.VBtn("save PNG", click="window.apmgsrnViewer.saveFrame()", variant="text", id="apm-save-frame")
            v.VBtn(
                "save TF (.json)",
                click="window.apmgsrnViewer.saveTransferFunction()",
                variant="text",
                id="apm-save-tf",
            )
        with v.VNavigationDrawer(permanent=True, width=340, location="left"):
            with html.Div(classes="pa-3"):
                html.Div("data", classes="apm-section")
                v.VSelect(
                    v_model=("source_name", None),
                    items=("entries", []),
                    label="model or volume",
                    density="compact",
                    hide_details=True,
                    id="apm-source-select",
                )
                with html.Div(v_show="time_steps > 1", classes="d-flex align-center mt-2", id="apm-time"):
                    v.VBtn(
                        "{{ time_playing ? 'pause' : 'play' }}",
                        click="time_playing = !time_playing",
                        variant="tonal",
                        size="small",
                        classes="mr-3",
                        id="apm-time-play",
                    )
                    v.VSlider(
                        v_model=("time_step", 0),
                        min=0,
                        max=("time_steps - 1",),
                        step=1,
                        hide_details=True,
                        density="compact",
                        id="apm-time-slider",
                    )
                html.Div("{{ time_label }}", v_show="time_steps > 1", classes="text-caption", id="apm-time-label")
                # Files under PATH the listing left out (unreadable, foreign, hostile), with the reason.
                with html.Details(v_if="skipped_count", classes="text-caption mt-1", id="apm-skipped"):
                    html.Summary("{{ skipped_count }} file(s) under the folder not listed")
                    html.Div("{{ line }}", v_for="(line, index) in skipped_files", key="index")
                html.Div("colour map", classes="apm-section")
                with html.Div(classes="d-flex align-center"):
                    v.VSelect(
                        v_model=("colormap", settings.colormap),
                        items=("colormaps", []),
                        density="compact",
                        hide_details=True,
                        id="apm-colormap-select",
                    )
                    v.VBtn(
                        "upload",
                        click="window.apmgsrnViewer.chooseUpload()",
                        variant="text",
                        size="small",
                        id="apm-upload-button",
                    )
                    html.Input(type="file", accept=".json,.xml", id="apm-upload", style="display:none")
                html.Div("opacity", classes="apm-section")
                html.Div(id="apm-tf-editor")
                html.Div(
                    "click: add point · drag: move · double-click or right-click: delete",
                    classes="text-caption text-medium-emphasis",
                )
                html.Div("value range", classes="apm-section")
                v.VRangeSlider(
                    v_model=("value_range", [0.0, 1.0]),
                    min=("data_min",),
                    max=("data_max",),
                    step=("value_step",),
                    hide_details=True,
                    density="compact",
                    id="apm-range",
                )
                html.Div(
                    "{{ Number(value_range[0]).toPrecision(4) }} … {{ Number(value_range[1]).toPrecision(4) }}",
                    classes="text-caption",
                )
                html.Div("sampling", classes="apm-section")
                v.VSlider(
                    v_model=("samples_per_ray", settings.samples_per_ray),
                    min=8,
                    max=512,
                    step=8,
                    label="samples / ray",
                    thumb_label=True,
                    hide_details=True,
                    density="compact",
                    id="apm-spp",
                )
                v.VSelect(
                    v_model=("batch_size", settings.batch_size),
                    items=("batch_sizes", []),
                    label="batch size (points per pass)",
                    density="compact",
                    hide_details=True,
                    classes="mt-2",
                    id="apm-batch",
                )
                v.VSelect(
                    v_model=("image_size", settings.image_width),
                    items=("image_sizes", []),
                    label="image size (pixels)",
                    density="compact",
                    hide_details=True,
                    classes="mt-2",
                    id="apm-image-size",
                )
                html.Div("statistics", classes="apm-section")
                html.Pre("{{ stats_text }}", classes="text-caption", style="white-space: pre-wrap", id="apm-stats")
        with v.VMain(), html.Div(id="apm-viewport"):
            with html.Div(id="apm-messages"):
                # Each message is one state key the page may only clear (upload_error is the page's own).
                for key, kind, element in (
                    ("error_message", "error", "apm-error"),
                    ("upload_error", "error", "apm-upload-error"),
                    ("saved_message", "success", "apm-saved"),
                ):
                    v.VAlert(
                        f"{{{{ {key} }}}}",
                        v_if=key,
                        type=kind,
                        density="compact",
                        closable=True,
                        click_close=f"{key} = ''",
                        id=element,
                        classes="mb-1",
                    )
            html.Img(
                src=("frame_src",),
                v_show="frame_src",
                id="apm-frame",
                draggable="false",
                raw_attrs=[':data-generation="frame_generation"', ':data-stride="frame_stride"'],
            )
            with html.Svg(
                id="apm-overlay-svg",
                v_show="frame_src && overlay_lines.length",
                raw_attrs=[
                    ':viewBox="`0 0 ${frame_width} ${frame_height}`"',
                    'preserveAspectRatio="xMidYMid meet"',
                ],
            ):
                HtmlElement(
                    "line",
                    v_for="(line, index) in overlay_lines",
                    key="index",
                    raw_attrs=[
                        ':x1="line[0]"', ':y1="line[1]"', ':x2="line[2]"', ':y2="line[3]"', ':stroke="line[4]"',
                        'stroke-width="1.5"', 'vector-effect="non-scaling-stroke"',
                    ],
                )
            html.Div(
                "{{ status_message || 'left drag: orbit · shift/middle drag: pan · wheel: zoom' }}",
                id="apm-overlay-text",
            )
    return layout
