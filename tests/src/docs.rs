//! Reading the repository's Markdown: the command lines of its `sh` blocks and of its inline
//! code, so that tests can run them or check what they name.

use std::path::{Path, PathBuf};

/// The repository root (this crate lives in `tests/`).
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the repository root")
        .to_path_buf()
}

/// The text of a file of the repository, by its path from the root.
pub fn read(rel: &str) -> String {
    std::fs::read_to_string(root().join(rel)).unwrap_or_else(|e| panic!("{rel}: {e}"))
}

/// The user's documents: README.md, every page of docs/ and deploy/README.md, by path from
/// the root, sorted.
pub fn user_docs() -> Vec<String> {
    let mut docs = vec!["README.md".to_string(), "deploy/README.md".to_string()];
    for entry in std::fs::read_dir(root().join("docs"))
        .expect("docs/")
        .flatten()
    {
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.ends_with(".md") {
            docs.push(format!("docs/{name}"));
        }
    }
    docs.sort();
    docs
}

/// The fenced blocks of a Markdown text: (info string, body). Panics on a fence left open, which
/// would swallow the rest of the page.
pub fn fenced_blocks(text: &str) -> Vec<(String, String)> {
    let mut blocks = Vec::new();
    let mut open: Option<(String, String)> = None;
    for line in text.lines() {
        let fence = line.trim_start().starts_with("```");
        match (&mut open, fence) {
            (None, true) => {
                open = Some((
                    line.trim().trim_start_matches('`').to_string(),
                    String::new(),
                ))
            }
            (Some(_), true) => blocks.push(open.take().expect("an open block")),
            (Some((_, body)), false) => {
                body.push_str(line);
                body.push('\n');
            }
            (None, false) => {}
        }
    }
    assert!(open.is_none(), "a fenced block is never closed");
    blocks
}

/// The commands of a text's `sh` blocks, one per line: comments, blank lines and a trailing
/// `&` left out.
pub fn sh_lines(text: &str) -> Vec<String> {
    fenced_blocks(text)
        .into_iter()
        .filter(|(info, _)| info == "sh")
        .flat_map(|(_, body)| command_lines(&body))
        .collect()
}

/// The commands of one `sh` block's body, as [`sh_lines`] reads them.
pub fn command_lines(body: &str) -> Vec<String> {
    body.lines()
        .map(|line| line.split(" #").next().unwrap_or("").trim())
        .filter(|c| !c.is_empty() && !c.starts_with('#'))
        .map(|c| c.trim_end_matches('&').trim().to_string())
        .collect()
}

/// The words of a command line as a shell splits them: at white space, except inside single or
/// double quotes, which are removed.
pub fn shell_words(line: &str) -> Vec<String> {
    let mut words = Vec::new();
    let (mut word, mut quote, mut started) = (String::new(), None, false);
    for c in line.chars() {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), c) => word.push(c),
            (None, '"' | '\'') => {
                quote = Some(c);
                started = true;
            }
            (None, c) if c.is_whitespace() => {
                if started {
                    words.push(std::mem::take(&mut word));
                    started = false;
                }
            }
            (None, c) => {
                word.push(c);
                started = true;
            }
        }
    }
    if started {
        words.push(word);
    }
    words
}

/// The inline code spans of a text outside its fenced blocks, a span broken over lines joined
/// with a space.
pub fn inline_code(text: &str) -> Vec<String> {
    let mut prose = String::new();
    let mut inside = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            inside = !inside;
            prose.push('\n');
            continue;
        }
        if !inside {
            prose.push_str(line);
            prose.push('\n');
        }
    }
    // Paragraph breaks end a span that was never closed (a stray backtick).
    prose
        .split("\n\n")
        .flat_map(|para| {
            para.split('`')
                .skip(1)
                .step_by(2)
                .map(|s| s.split_whitespace().collect::<Vec<_>>().join(" "))
                .collect::<Vec<_>>()
        })
        .filter(|s| !s.is_empty())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blocks_lines_and_spans_are_read_as_written() {
        let text = "a `salient run\nX --threads 2` b\n\n```sh\nsalient worker &   # one\n# c\n\nscripts/x.sh 2\n```\n```toml\n[a]\n```\n";
        assert_eq!(inline_code(text), ["salient run X --threads 2"]);
        assert_eq!(sh_lines(text), ["salient worker", "scripts/x.sh 2"]);
        assert_eq!(fenced_blocks(text)[1], ("toml".into(), "[a]\n".into()));
    }

    #[test]
    #[should_panic(expected = "never closed")]
    fn an_open_fence_is_refused() {
        fenced_blocks("```\nsalient orbit\n");
    }
}
