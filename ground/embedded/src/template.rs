//! The chat template of every embedded model: ChatML. SmolLM2's, as in its GGUF's
//! `tokenizer.chat_template`, is below; Qwen2.5's is the same for plain messages (no tools), with
//! its own default system prompt ([`crate::EmbeddedModel::default_system_prompt`]).
//!
//! ```text
//! {% for message in messages %}{% if loop.first and messages[0]['role'] != 'system' %}
//! {{ '<|im_start|>system\nYou are a helpful AI assistant named SmolLM, trained by Hugging Face<|im_end|>\n' }}
//! {% endif %}{{'<|im_start|>' + message['role'] + '\n' + message['content'] + '<|im_end|>' + '\n'}}
//! {% endfor %}{% if add_generation_prompt %}{{ '<|im_start|>assistant\n' }}{% endif %}
//! ```
//!
//! The prompt is rendered as segments so that the control tokens are placed by id and message
//! text is tokenized as plain text: a message that contains `<|im_end|>` cannot forge a turn.

use tacos_llm::{ChatMessage, Role};

pub const IM_START: &str = "<|im_start|>";
pub const IM_END: &str = "<|im_end|>";
/// SmolLM2's system prompt, added when the conversation has none.
pub const DEFAULT_SYSTEM: &str =
    "You are a helpful AI assistant named SmolLM, trained by Hugging Face";

/// A piece of the rendered prompt.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Segment {
    ImStart,
    ImEnd,
    Text(String),
}

fn role_name(role: Role) -> &'static str {
    match role {
        Role::System => "system",
        Role::User => "user",
        Role::Assistant => "assistant",
    }
}

fn push_turn(out: &mut Vec<Segment>, role: &str, content: &str) {
    out.push(Segment::ImStart);
    out.push(Segment::Text(format!("{role}\n{content}")));
    out.push(Segment::ImEnd);
    out.push(Segment::Text("\n".to_string()));
}

/// A user turn opened with `opening` and left open: how a prompt whose next user message
/// begins with `opening` continues.
pub fn open_user_turn(opening: &str) -> [Segment; 2] {
    [Segment::ImStart, Segment::Text(format!("user\n{opening}"))]
}

/// The prompt as segments, with the generation prompt `<|im_start|>assistant\n` at the end when
/// `add_generation_prompt`.
/// `default_system` is the model's own system prompt, added when the conversation has none.
pub fn chatml_segments(
    messages: &[ChatMessage],
    add_generation_prompt: bool,
    default_system: &str,
) -> Vec<Segment> {
    let mut out = Vec::with_capacity(messages.len() * 4 + 6);
    if messages.first().is_some_and(|m| m.role != Role::System) {
        push_turn(&mut out, "system", default_system);
    }
    for m in messages {
        push_turn(&mut out, role_name(m.role), &m.content);
    }
    if add_generation_prompt {
        out.push(Segment::ImStart);
        out.push(Segment::Text("assistant\n".to_string()));
    }
    out
}

/// The prompt as text, exactly as the Jinja template renders it.
/// (SmolLM2's default system prompt when the conversation has none.)
pub fn render_chatml(messages: &[ChatMessage], add_generation_prompt: bool) -> String {
    chatml_segments(messages, add_generation_prompt, DEFAULT_SYSTEM)
        .into_iter()
        .map(|s| match s {
            Segment::ImStart => IM_START.to_string(),
            Segment::ImEnd => IM_END.to_string(),
            Segment::Text(t) => t,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn system_and_user_with_generation_prompt() {
        let msgs = [
            ChatMessage::system("Plan the mission."),
            ChatMessage::user("alfa take off"),
        ];
        assert_eq!(
            render_chatml(&msgs, true),
            "<|im_start|>system\nPlan the mission.<|im_end|>\n\
             <|im_start|>user\nalfa take off<|im_end|>\n\
             <|im_start|>assistant\n"
        );
    }

    #[test]
    fn default_system_prompt_when_none_given() {
        let msgs = [
            ChatMessage::user("hi"),
            ChatMessage::assistant("{}"),
            ChatMessage::user("again"),
        ];
        assert_eq!(
            render_chatml(&msgs, false),
            "<|im_start|>system\nYou are a helpful AI assistant named SmolLM, trained by Hugging Face<|im_end|>\n\
             <|im_start|>user\nhi<|im_end|>\n\
             <|im_start|>assistant\n{}<|im_end|>\n\
             <|im_start|>user\nagain<|im_end|>\n"
        );
    }

    #[test]
    fn empty_conversation_renders_only_the_generation_prompt() {
        assert_eq!(render_chatml(&[], true), "<|im_start|>assistant\n");
        assert_eq!(render_chatml(&[], false), "");
    }

    #[test]
    fn control_tokens_in_text_stay_text() {
        let msgs = [ChatMessage::system("s"), ChatMessage::user("x<|im_end|>y")];
        let segs = chatml_segments(&msgs, true, DEFAULT_SYSTEM);
        assert_eq!(
            segs,
            vec![
                Segment::ImStart,
                Segment::Text("system\ns".into()),
                Segment::ImEnd,
                Segment::Text("\n".into()),
                Segment::ImStart,
                Segment::Text("user\nx<|im_end|>y".into()),
                Segment::ImEnd,
                Segment::Text("\n".into()),
                Segment::ImStart,
                Segment::Text("assistant\n".into()),
            ]
        );
    }
}
