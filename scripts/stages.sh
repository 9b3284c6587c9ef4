# Sourced by scripts/main.sh and scripts/gpu.sh: times each stage of a pipeline and writes the
# seconds to one JSON file, so that a run's figure and its parts come from the run itself.
#
#   stage NAME COMMAND...        run COMMAND, adding its seconds to NAME's
#   write_timings FILE K=V ...   FILE gets {"K": V, ..., "<stage>_s": seconds, ...,
#                                "total_s": their sum}, stages in the order they first ran;
#                                a V that is a number is written as one, any other as a string
declare -A SPENT=()
STAGES=()
stage() {
  local name=$1 start=$SECONDS
  shift
  "$@"
  if [[ -z "${SPENT[$name]+set}" ]]; then STAGES+=("$name"); SPENT[$name]=0; fi
  SPENT[$name]=$((SPENT[$name] + SECONDS - start))
}
write_timings() {
  local file=$1 total=0 name pair format
  shift
  {
    printf '{'
    for pair in "$@"; do
      if [[ "${pair#*=}" =~ ^-?[0-9]+(\.[0-9]+)?$ ]]; then format='"%s": %s, '
      else format='"%s": "%s", '; fi
      # shellcheck disable=SC2059
      printf "$format" "${pair%%=*}" "${pair#*=}"
    done
    for name in "${STAGES[@]}"; do
      printf '"%s_s": %s, ' "$name" "${SPENT[$name]}"
      total=$((total + SPENT[$name]))
    done
    printf '"total_s": %s}\n' "$total"
  } > "$file"
}
