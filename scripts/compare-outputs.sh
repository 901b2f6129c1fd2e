# Sourced by scripts/soak.sh and scripts/slurm-e2e.sh: whether the output folder of `salient
# results` (B) equals that of `salient run` on the same spec (A) — the same files, per-cell files
# byte for byte, and the tables and run.json without what measures the run rather than its
# result (CPU and wall seconds, dropped work, out_dir, forecast_from; docs/outputs.md).

normalized() { # normalized FILE
  case ${1##*/} in
    run.json | table.json)
      sed -E '/^[[:space:]]*"(cpu_s|wall_s|orbits_dropped|steps_dropped|steps_total|out_dir|forecast_from)":/d' "$1"
      ;;
    # The last four columns: dropped, % steps dropped, CPU s, wall s (Markdown rows also end
    # in an empty field after the last '|').
    table.csv) awk -F, '{ s = $1; for (i = 2; i <= NF - 4; i++) s = s FS $i; print s }' "$1" ;;
    table.md) awk -F'|' '{ s = $1; for (i = 2; i <= NF - 5; i++) s = s FS $i; print s }' "$1" ;;
    *) cat "$1" ;;
  esac
}

compare_outputs() { # compare_outputs A B: prints the differences; status 1 when there are any
  local a=$1 b=$2 la lb f bad=0
  la=$(cd "$a" && find . -type f | sed 's,^\./,,' | LC_ALL=C sort)
  lb=$(cd "$b" && find . -type f | sed 's,^\./,,' | LC_ALL=C sort)
  if [[ $la != "$lb" ]]; then
    echo "the file sets differ (< salient run, > salient results):"
    diff <(echo "$la") <(echo "$lb") | grep '^[<>]' || true
    bad=1
  fi
  while read -r f; do
    [[ -n $f && -f $b/$f ]] || continue
    case ${f##*/} in
      run.json | table.json | table.csv | table.md)
        if ! cmp -s <(normalized "$a/$f") <(normalized "$b/$f"); then
          echo "$f differs beyond timings:"
          diff <(normalized "$a/$f") <(normalized "$b/$f") | head -n 12 || true
          bad=1
        fi
        ;;
      *)
        if ! cmp -s "$a/$f" "$b/$f"; then
          echo "$f differs: $(cmp "$a/$f" "$b/$f" 2>&1 | head -n 1)"
          bad=1
        fi
        ;;
    esac
  done <<<"$la"
  return "$bad"
}
