# The part of a QEMU board's run-tests.sh after the build, shared by boards/qemu-mps2 (Cortex-M7)
# and boards/qemu-mps3-m55 (Cortex-M55): builds the instruction-count plugin, runs the frame
# firmware, checks its MUIR-RESULT line against the expected file, reports the stack and the
# instructions per frame. Sourced by the board script with these set:
#   name      prefix of the messages (qemu-mps2, ...)     machine  QEMU machine (mps2-an500, ...)
#   root      repository root                             elf      the firmware ELF (stereo)
#   expected  the expected*.txt file                      size     WxH of the frame
#   tmp       a scratch folder
# and say/die defined. The engine's MACs come from `muir macs` (test profile, see below).

# What the messages call the expected file: its path from the repository root.
shown="${expected#"$root/"}"

plugin_args=()
plugin_src="$root/../shared/tools/qemu-icount/icount.c"
if [ -f "$plugin_src" ] && command -v gcc >/dev/null; then
    if gcc -O2 -shared -fPIC -fvisibility=hidden -o "$tmp/libicount.so" "$plugin_src"; then
        start=$(nm "$elf" | awk '$3=="bench_start"{print $1}')
        end=$(nm "$elf" | awk '$3=="bench_end"{print $1}')
        [ -n "$start" ] && [ -n "$end" ] || die "bench_start/bench_end markers not found in $elf"
        plugin_args=(-plugin "$tmp/libicount.so,start=0x$start,end=0x$end" -d plugin)
    else
        say "warning: could not build the icount plugin; running without instruction counts"
    fi
else
    say "warning: $plugin_src (or gcc) not found; running without instruction counts"
fi

say "running on qemu-system-arm -M $machine"
t0=$(date +%s.%N)
set +e
timeout "${QEMU_TIMEOUT:-600}" qemu-system-arm -M "$machine" -nographic \
    -semihosting-config enable=on,target=native "${plugin_args[@]}" -kernel "$elf" >"$tmp/qemu.log" 2>&1
status=$?
set -e
wall=$(echo "$(date +%s.%N) $t0" | awk '{printf "%.1f", $1 - $2}')
grep -v '^icount:' "$tmp/qemu.log" || true
[ "$status" -ne 124 ] || die "QEMU timed out after ${QEMU_TIMEOUT:-600} s"
[ "$status" -eq 0 ] || die "the firmware exited with status $status"
say "firmware exit status 0, QEMU wall time $wall s"

got=$(grep -m1 '^MUIR-RESULT ' "$tmp/qemu.log" | tr -d '\r' || true)
want=$(grep -m1 '^MUIR-RESULT ' "$expected" || true)
[ -n "$got" ] || die "the firmware printed no MUIR-RESULT line"
if [ "$got" != "$want" ]; then
    echo "  expected: $want ($shown)" >&2
    echo "  firmware: $got" >&2
    die "the firmware's results differ from $shown (the host test checks the host engine against the same file)"
fi
say "MUIR-RESULT matches $shown (bit-exact with the host engine via cargo test --test firmware)"
stack=$(grep -m1 '^MUIR-STACK ' "$tmp/qemu.log" | tr -d '\r' || true)
[ -n "$stack" ] || die "the firmware printed no MUIR-STACK line (painted-stack high-water mark)"
say "RAM: ${stack#MUIR-STACK } (bytes: stack high-water mark of the frame, painted; static arena from the plan)"

if [ ${#plugin_args[@]} -gt 0 ]; then
    # Region 0 is empty (the markers' own cost), region 1 the frame.
    empty=$(awk -F'delta=' '/^icount: region 0 /{print $2}' "$tmp/qemu.log")
    region=$(awk -F'delta=' '/^icount: region 1 /{print $2}' "$tmp/qemu.log")
    [ -n "$empty" ] && [ -n "$region" ] || die "the icount plugin reported no frame region"
    insns=$((region - empty))
    say "icount: region delta=$region, markers $empty -> $insns instructions per frame"
    w=${size%x*} h=${size#*x}
    # The iterations the frame ran (fewer than the config's with adaptive iterations), from
    # its result line; the MACs are those of that many iterations.
    iters=$(echo "$got" | sed -n 's/.* iters=\([0-9]*\).*/\1/p')
    # `muir macs` prints a Markdown table in G (3 decimals); the test profile reuses what
    # `cargo test` built (scripts/test.sh), where --release would build the whole crate again.
    if gmacs=$(cd "$root" && cargo run -q --profile test --bin muir -- macs --config muir-slim --size "${w}x${h}" ${iters:+--iters "$iters"} \
        | awk -F'|' '/\*\*engine total\*\*/{gsub(/ /, "", $4); print $4}') && [ -n "$gmacs" ]; then
        awk -v name="$name" -v g="$gmacs" -v n="$insns" -v it="${iters:-all}" 'BEGIN {
            printf "%s: engine MACs per frame %.3f G (muir macs, %s iterations) -> %.4f MAC/instruction, %.2f instructions/MAC\n",
                name, g, it, g * 1e9 / n, n / (g * 1e9) }'
    else
        say "warning: could not read the engine total of 'muir macs'; MACs per instruction not computed"
    fi
fi
say "passed"
