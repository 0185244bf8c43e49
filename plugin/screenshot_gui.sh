#!/usr/bin/env bash
# Screenshots of the ParaView GUI with the plugin, for the README (a doc tool, not run in CI).
#
#   plugin/screenshot_gui.sh [OUT_DIR]        (default: docs/images)
#
# Starts a private Xvfb (1600x1400), runs `paraview --dr` with PV_PLUGIN_PATH=dvr_perception/paraview and the
# scene plugin/screenshot/gui_scene.py (neghip volume-rendered with its preset, an *Optimize
# Transfer Function* filter selected) and writes
#
#   OUT_DIR/paraview_gui.png       the whole window: the filter's Properties panel
#   OUT_DIR/paraview_gui_menu.png  the volume selected, Filters > DVR Perception open
#                                  (the top-left 1100x560 pixels)
#
# Needs paraview, Xvfb, xdotool, xwd (x11-apps) and ImageMagick's convert:
#   apt-get install paraview xvfb xdotool x11-apps imagemagick
# The mouse positions below are those of ParaView 5.11 (Debian bookworm) with its default
# fonts on this screen size; set DVR_SCREENSHOT_FILTERS_XY etc. ("X Y") for another build.
# DVR_SCREENSHOT_VOLUME picks another volume (default ../shared/data/neghip.nhdr).
set -euo pipefail

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(dirname "$HERE")
PLUGIN_DIR="$ROOT/dvr_perception/paraview"
OUT=${1:-$ROOT/docs/images}
SCREEN=1600x1400
FILTERS_XY=${DVR_SCREENSHOT_FILTERS_XY:-215 10}     # "Filters" in the menu bar
CATEGORY_XY=${DVR_SCREENSHOT_CATEGORY_XY:-285 261}  # "DVR Perception" in that menu
ITEM_XY=${DVR_SCREENSHOT_ITEM_XY:-575 261}          # "Optimize Transfer Function" in its submenu
SOURCE_XY=${DVR_SCREENSHOT_SOURCE_XY:-88 196}       # "neghip.nhdr" in the Pipeline Browser

for tool in paraview Xvfb xdotool xwd convert; do
    command -v "$tool" >/dev/null || { echo "screenshot_gui.sh: $tool not found" >&2; exit 2; }
done
mkdir -p "$OUT"
work=$(mktemp -d)
xvfb_pid="" pv_pid=""
cleanup() {
    [ -n "$pv_pid" ] && kill "$pv_pid" 2>/dev/null || true
    [ -n "$xvfb_pid" ] && kill "$xvfb_pid" 2>/dev/null || true
    rm -rf "$work"
}
trap cleanup EXIT

# a private X server; -displayfd picks a free display number; -noreset: a server that resets
# when its last client leaves refuses the clients connecting meanwhile
Xvfb -displayfd 3 -screen 0 "${SCREEN}x24" -nolisten tcp -noreset 3>"$work/display" 2>"$work/xvfb.log" &
xvfb_pid=$!
for _ in $(seq 100); do [ -s "$work/display" ] && break; sleep 0.1; done
export DISPLAY=":$(head -n1 "$work/display")"

PYTHONPATH="$PLUGIN_DIR/pvsite${PYTHONPATH:+:$PYTHONPATH}" PV_PLUGIN_PATH="$PLUGIN_DIR" \
    DVR_SCREENSHOT_PLUGIN_DIR="$PLUGIN_DIR" DVR_SCREENSHOT_READY="$work/ready" \
    paraview --dr --script="$HERE/screenshot/gui_scene.py" >"$work/paraview.log" 2>&1 &
pv_pid=$!
for _ in $(seq 180); do
    [ -f "$work/ready" ] && break
    kill -0 "$pv_pid" 2>/dev/null || { cat "$work/paraview.log" >&2; exit 1; }
    sleep 1
done
[ -f "$work/ready" ] || { echo "screenshot_gui.sh: the scene did not finish" >&2; exit 1; }

window=$(xdotool search --sync --name '^ParaView [0-9]' | head -n1)
xdotool windowmove "$window" 0 0 windowsize "$window" "${SCREEN%x*}" "${SCREEN#*x}"

idle() {  # wait until paraview has used < 0.1 s of CPU in a second (at most 60 s)
    local before after
    for _ in $(seq 60); do
        before=$(awk '{print $14 + $15}' "/proc/$pv_pid/stat")
        sleep 1
        after=$(awk '{print $14 + $15}' "/proc/$pv_pid/stat")
        [ $((after - before)) -lt 10 ] && return 0
    done
}
hover() {  # hover X Y: two motion events (Qt opens submenus on motion), then wait
    xdotool mousemove $(($1 - 6)) "$2"
    sleep 0.5
    xdotool mousemove "$1" "$2"
    sleep 1
    idle
}
idle
# the volume's LUT warning opens "Output Messages" over the view: hide that window
for w in $(xdotool search --name '^Output Messages$' || true); do xdotool windowunmap "$w"; done
xdotool mousemove 1200 $((${SCREEN#*x} - 10))  # park the pointer on the status bar
sleep 1
idle

shot() {  # shot FILE [convert options]: capture the screen as PNG
    local file=$1
    shift
    xwd -root -silent | convert xwd:- "$@" -strip "png:$file"
    echo "wrote $file"
}
shot "$OUT/paraview_gui.png"

# select the volume (the filters are enabled for image data), then
# Filters > DVR Perception with the pointer on Optimize Transfer Function
# shellcheck disable=SC2086  # the positions are "X Y" pairs
xdotool mousemove $SOURCE_XY click 1
sleep 1
idle
# shellcheck disable=SC2086
xdotool mousemove $FILTERS_XY click 1
sleep 1
idle
# shellcheck disable=SC2086
hover $CATEGORY_XY
# shellcheck disable=SC2086
hover $ITEM_XY
shot "$OUT/paraview_gui_menu.png" -crop 1100x560+0+0 +repage
xdotool key Escape Escape
